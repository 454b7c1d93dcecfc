"""Hand shape from bone lengths (paper Eq. 8), per frame and over a track.

    E(beta) = sum_b ( l_b(beta) / l_ref(beta) - r_b )^2 + lambda |beta|^2

r_b are the bone-length ratios of the predicted joints to the reference bone 0 -> 9
(scale-normalized predictions fix only ratios, so shape is relative). The model's
`hand_size` coefficient is left out of the fit and stays 0: it scales the whole hand, and
the small changes of proportion that come with it made a free fit trade it against
the other coefficients (on a real clip it ran to -4.75, a 7.2 cm instead of a 10 cm palm).
The metric size is set afterwards, from the person's hand length or the population's
(HandModel.sized, PoseEstimator). Coefficients that only thicken fingers cannot be seen
either; the prior keeps them near 0.
The model's rest joints are linear in beta, so the ratios are nearly linear in beta:
ShapeFitter solves the damped linear least squares at beta = 0 in closed form (one
precomputed (B, n_bones) matrix), then takes Gauss-Newton steps with the exact ratios and
Jacobian at the current beta (a B x B solve each).
"""
import numpy as np

from handmocap.perception.skeleton import BONES, FINGER_TIPS, REF_BONE, normalize_joints

_REF_INDEX = BONES.index(REF_BONE)
BONES_WITH_TIPS = tuple(i for i in range(len(BONES)) if i != _REF_INDEX)                     # 19
BONES_WITHOUT_TIPS = tuple(i for i in BONES_WITH_TIPS if BONES[i][1] not in FINGER_TIPS)    # 14
_PARENT = np.array([p for p, _ in BONES])
MAX_SHAPES = 16   # messages/HandShape.json: shapes maxItems
_CHILD = np.array([c for _, c in BONES])


def bone_lengths(xyz):
    """(..., 21, 3) joints -> (..., 20) lengths of BONES, same unit."""
    xyz = np.asarray(xyz, dtype=np.float64)
    return np.linalg.norm(xyz[..., _CHILD, :] - xyz[..., _PARENT, :], axis=-1)


def bone_ratios(xyz):
    """(..., 21, 3) joints -> (..., 20) bone lengths divided by the reference bone 0 -> 9."""
    lengths = bone_lengths(xyz)
    return lengths / np.maximum(lengths[..., _REF_INDEX:_REF_INDEX + 1], 1e-12)


class ShapeFitter:
    """Fits beta to bone ratios of one hand model.

    model: a HandModel (uses rest_joints' linear form j_template + j_shapedirs beta).
    prior: lambda of Eq. 8 (in squared-ratio units per unit beta^2).
    include_tips: fit the 19 non-reference bones (True) or the 14 without fingertips.
    steps: Gauss-Newton refinements after the closed-form linear solve.
    """

    def __init__(self, model, prior=1e-6, include_tips=True, steps=2, fixed=("hand_size",)):
        self.j_template = np.asarray(model.j_template, dtype=np.float64)       # (21,3)
        self.j_shapedirs = np.asarray(model.j_shapedirs, dtype=np.float64)     # (21,3,B)
        self.num_betas = self.j_shapedirs.shape[-1]
        # the coefficients fitted (F,); those named in `fixed` stay 0
        self.free = np.array([k for k, name in enumerate(model.beta_names) if name not in fixed])
        self.prior = float(prior)
        self.bones = np.array(BONES_WITH_TIPS if include_tips else BONES_WITHOUT_TIPS)
        self.steps = steps
        r0, jac0 = self.ratios_and_jacobian(np.zeros(self.num_betas))
        self.r0 = r0
        self.jac0 = jac0[np.ix_(self.bones, self.free)]                         # (bones, F)
        self.normal0 = self.jac0.T @ self.jac0
        # beta = (JᵀJ + λI)⁻¹ Jᵀ (r - r0): the first Gauss-Newton step from beta = 0
        self.linear_solve = np.linalg.solve(self.normal0 + self.prior * np.eye(len(self.free)), self.jac0.T)

    def ratios_and_jacobian(self, beta):
        """Model bone ratios (20,) at beta and their derivative (20, B)."""
        joints = self.j_template + self.j_shapedirs @ beta                      # (21,3)
        vec = joints[_CHILD] - joints[_PARENT]                                  # (20,3)
        length = np.linalg.norm(vec, axis=-1)
        dvec = self.j_shapedirs[_CHILD] - self.j_shapedirs[_PARENT]             # (20,3,B)
        dlength = np.einsum("bc,bck->bk", vec / length[:, None], dvec)          # (20,B)
        ref, dref = length[_REF_INDEX], dlength[_REF_INDEX]
        ratios = length / ref
        jac = (dlength * ref - length[:, None] * dref[None]) / ref ** 2
        return ratios, jac

    def fit_ratios(self, ratios, prior=None):
        """beta (B,) minimising Eq. 8 for observed ratios (20,) (BONES order); prior
        overrides lambda (e.g. a tracker's, shrinking as frames accumulate)."""
        target = np.asarray(ratios, dtype=np.float64)[self.bones]
        prior = self.prior if prior is None else float(prior)
        eye = prior * np.eye(len(self.free))
        if prior == self.prior:
            free = self.linear_solve @ (target - self.r0[self.bones])
        else:
            free = np.linalg.solve(self.normal0 + eye, self.jac0.T @ (target - self.r0[self.bones]))
        beta = np.zeros(self.num_betas)
        for _ in range(self.steps):
            beta[self.free] = free
            r, jac = self.ratios_and_jacobian(beta)
            jac = jac[np.ix_(self.bones, self.free)]
            free = free + np.linalg.solve(jac.T @ jac + eye, jac.T @ (target - r[self.bones]) - prior * free)
        beta[self.free] = free
        return beta

    def fit(self, xyz):
        """beta (B,) from predicted joints (21,3) in any unit (e.g. root-relative, normalized)."""
        return self.fit_ratios(bone_ratios(xyz))

    def model_ratios(self, beta):
        """(20,) bone ratios of the model at beta."""
        return self.ratios_and_jacobian(np.asarray(beta, dtype=np.float64))[0]


class RecentRows:
    """The last `window` rows (C,) in arrival order, as one contiguous (n, C) array view.

    A deque of rows had to be stacked into an array on every frame (60 us for 600 frames);
    here rows are written into a buffer of twice the window, and the live block is moved
    back to the start when it reaches the end (once per `window` rows)."""

    def __init__(self, window, columns):
        self.window = window
        self.buffer = np.empty((2 * window, columns))
        self.start = self.stop = 0

    def __len__(self):
        return self.stop - self.start

    def append(self, row):
        if self.stop == len(self.buffer):
            self.buffer[:len(self)] = self.buffer[self.start:self.stop]
            self.start, self.stop = 0, len(self)
        self.buffer[self.stop] = row
        self.stop += 1
        if len(self) > self.window:
            self.start += 1

    def clear(self):
        self.start = self.stop = 0

    def rows(self):
        """(n, C) view, oldest first (valid until the next append)."""
        return self.buffer[self.start:self.stop]


def _middle(x):
    """The order statistics np.median averages, per column of (n, C) finite data: (lo, hi)
    (C,) each, equal when n is odd. One partition for both median(x) and median(f(x)) of
    any increasing f."""
    n = len(x)
    k = [n // 2 - 1, n // 2] if n % 2 == 0 else [n // 2]
    part = np.partition(x, k, axis=0)
    return part[k[0]], part[k[-1]]


def _median_of(lo, hi):
    """np.median's value from its middle order statistics (the mean of the two, or the one)."""
    return lo if lo is hi else (lo + hi) / 2.0


def _column_median(x):
    """np.median(x, axis=0) for finite (n, C) x (the same value, without its overhead)."""
    return _median_of(*_middle(x))


class ShapeTracker:
    """Running shape estimate for one tracked hand (shape is constant per person).

    Each update adds a frame's squared bone lengths. The estimate uses, per bone, a
    trimmed mean of squared lengths (frames further than `trim` robust SDs from the
    median are dropped: outlier frames), minus the bias that joint noise adds to squared
    lengths (3 sigma_d^2, sigma_d^2 estimated from how much rigid bones' lengths vary over
    frames), then fits beta to the ratios of those lengths. Frames are kept in a window
    of `window` (RecentRows), so a re-identified track recovers.

    >>> tracker = ShapeTracker(ShapeFitter(HandModel.load()))
    >>> beta, n = tracker.update(xyz_rel)     # per frame
    """

    def __init__(self, fitter, window=600, trim=3.0, min_frames_for_noise=8, prior_until_noise_known=1e-3,
                 refresh_every=8, refresh_all_until=64, refit_every=8):
        self.fitter = fitter
        # past `refresh_all_until` frames, beta is fitted again every this many frames only (its
        # trimmed means and Gauss-Newton steps cost ~0.3 ms; one frame moves beta by ~1/window)
        self.refit_every = refit_every
        self._since_fit = 0
        # the median and MAD of a full window take two partitions of (600, 20..40) values,
        # ~0.45 ms a frame; one frame moves them by ~1/window, so past `refresh_all_until`
        # frames they are recomputed every `refresh_every` frames (the trimmed mean itself,
        # over every frame in the window, still every frame)
        self.refresh_every = refresh_every
        self.refresh_all_until = refresh_all_until
        self._robust = None        # (median (40,), spread of sq (20,), noise variance), from
        self._robust_age = 0       # this many frames ago
        self.prior_until_noise_known = prior_until_noise_known   # strong shrinkage for the first frames
        # per frame: squared bone lengths (20) and the lengths (20), kept side by side so the
        # square roots are taken once per frame, not over the whole window every frame
        self.frames = RecentRows(window, 2 * len(BONES))
        self.trim = trim
        self.min_frames_for_noise = min_frames_for_noise
        self.beta = np.zeros(fitter.num_betas)

    @property
    def n_samples(self):
        return len(self.frames)

    @property
    def sq_lengths(self):
        """(n, 20) squared bone lengths of the frames in the window, oldest first."""
        return self.frames.rows()[:, :len(BONES)]

    def reset(self):
        self.frames.clear()
        self._robust = None
        self._since_fit = 0
        self.beta = np.zeros(self.fitter.num_betas)

    def update(self, xyz):
        """Add one frame's joints (21,3) (frames with non-finite or degenerate joints are
        skipped). Returns (beta (B,), number of frames in the estimate)."""
        sq = bone_lengths(xyz) ** 2
        if np.all(np.isfinite(sq)) and sq[_REF_INDEX] > 0:
            # not rescaled per frame: rescaling by a noisy reference bone would spread its
            # noise over every bone; bones are rigid in any fixed unit (normalized or metres)
            self.frames.append(np.concatenate([sq, np.sqrt(sq)]))
            self._since_fit += 1
            self._robust_age += 1
            if self.n_samples < self.refresh_all_until or self._since_fit >= self.refit_every:
                self._since_fit = 0
                ratios, ratio_var = self.ratios()
                # MAP weight of the N(0, I) prior on beta: variance of the averaged ratios
                self.beta = self.fitter.fit_ratios(ratios, prior=max(self.fitter.prior, ratio_var / self.n_samples))
        return self.beta.copy(), self.n_samples

    def ratios(self):
        """Current robust bone-ratio estimate (20,) and the per-frame ratio noise variance."""
        both = self.frames.rows()
        sq = both[:, :len(BONES)]                                               # (n,20); lengths beside
        if len(sq) < self.min_frames_for_noise:
            ratios = np.sqrt(np.median(sq, axis=0) / np.median(sq[:, _REF_INDEX]))
            return ratios, self.prior_until_noise_known
        if self._robust is None or len(sq) < self.refresh_all_until or self._robust_age >= self.refresh_every:
            self._robust, self._robust_age = self._robust_stats(both), 0
        med, spread, noise_var = self._robust
        keep = np.abs(sq - med) <= self.trim * spread
        mean_sq = np.sum(sq * keep, axis=0) / np.maximum(keep.sum(0), 1)
        corrected = np.maximum(mean_sq - 3.0 * noise_var, 0.05 * mean_sq)
        # a ratio l/l_ref carries the noise of both lengths: var ≈ sigma_d^2 (1 + r^2) / l_ref^2
        ratio_var = 2.0 * noise_var / corrected[_REF_INDEX]
        return np.sqrt(corrected / corrected[_REF_INDEX]), ratio_var

    @staticmethod
    def _robust_stats(both):
        """Per bone, of (n, 40) squared lengths and lengths: the median squared length (20,),
        the robust SD of squared lengths (20,), and the joint-noise variance per bone-vector
        coordinate, from the spread of the lengths of rigid bones."""
        sq = both[:, :len(BONES)]
        # lengths = sqrt(sq) keeps the order: one partition gives both medians (np.median's values)
        lo, hi = _middle(sq)
        med = _median_of(lo, hi)
        lmed = _median_of(np.sqrt(lo), np.sqrt(hi))
        mad = _column_median(np.abs(both - np.concatenate([med, lmed])))   # MAD of sq, of lengths
        spread = 1.4826 * mad[:len(BONES)] + 1e-12
        return med, spread, np.median((1.4826 * mad[len(BONES):]) ** 2)


class ShapeEstimator:
    """Shape trackers of all live tracks of one hand model (a HandModel); the shape node's
    and HandTracker's per-frame step."""

    def __init__(self, model, forget_after_s: float = 2.0, window: int = 600):
        self.model = model
        self.fitter = ShapeFitter(model)
        self.forget_after_s = forget_after_s
        self.window = window
        self.tracks: dict[int, tuple[ShapeTracker, str, float]] = {}
        self._rest_cache: dict[int, tuple[np.ndarray, dict]] = {}     # track id -> (beta, its fields)

    def update(self, hands: list[dict], now: float) -> list[dict]:
        """hands: HandKeypoints hands; returns HandShape shapes of every live track."""
        for h in hands:
            tracker = self.tracks.get(h["track_id"], (None,))[0] or ShapeTracker(self.fitter, window=self.window)
            tracker.update(h["xyz_rel"])
            self.tracks[h["track_id"]] = (tracker, h["handedness"], now)
        stale = [t for t, (_, _, seen) in self.tracks.items() if now - seen > self.forget_after_s]
        # at most MAX_SHAPES (HandShape's schema limit): the tracks seen longest ago go first
        by_age = sorted((t for t in self.tracks if t not in stale), key=lambda t: self.tracks[t][2])
        for tid in stale + by_age[:max(0, len(by_age) - MAX_SHAPES)]:
            del self.tracks[tid]
            self._rest_cache.pop(tid, None)
        out = []
        for tid, (tracker, handedness, _) in sorted(self.tracks.items()):
            out.append({"track_id": tid, "handedness": handedness, **self._rest_of(tid, tracker.beta),
                        "samples": tracker.n_samples})
        return out

    def _rest_of(self, tid, beta):
        """beta, rest_xyz and bone_ratios (float32) of a track, kept while its beta stays the
        same (ShapeTracker refits it every few frames only)."""
        kept_beta, fields = self._rest_cache.get(tid, (None, None))
        if kept_beta is None or not np.array_equal(kept_beta, beta):
            rest = normalize_joints(self.model.rest_joints(beta))
            fields = {"beta": beta.astype(np.float32), "rest_xyz": rest.astype(np.float32),
                      "bone_ratios": bone_ratios(rest).astype(np.float32)}
            self._rest_cache[tid] = (beta.copy(), fields)
        return fields
