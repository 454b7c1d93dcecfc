"""DetNet's training batches and their augmentation.

Each batch (drawn from numpy generator [seed, iteration], so a resumed run sees the
batches the uninterrupted run would have) mixes:
* synthetic crops (handsynth shards, --data): all heads. Left hands are mirrored to the
  right and the 3D label's x negated (rotations.mirror_points);
* real hand crops with 2D labels: howiema_lstm_pm subject 001, the MediaPipe
  pseudo-labels of real_data.TRAIN_VIDEOS (weight = MediaPipe's score) and, since cache
  v5, of every video/wild clip, 11K Hands person and images/scenes photo but the people
  held back by name (real_data.WILD_HELD_BACK, ELEVEN_K_HELD_BACK), all through
  real_data.reliable_hands; cut like the detector cuts (square around the keypoint box x
  1.3) with jitter. With --real-3d W the
  video crops' 3D heads also learn MediaPipe's world landmarks (root-relative and
  scale-normalized like the synthetic labels; weight W x score): the only 3D on real
  pixels there is, where the paper's real data has 2D only (zero 3D weight, the default);
* negatives (presence 0, heatmaps 0): real video crops away from every labelled hand of
  the frame, crops of the forearm beyond each labelled wrist (`arm_crop`: a track that
  slid up the arm must lose its presence), and procedural background textures
  (handmocap.training.synth.backgrounds); with --part-neg P, that share of them close-ups of part
  of a real hand (`part_crop`: a fingertip or the knuckles seen too close to be a whole
  hand, as a finder box on a photo-filling hand shows it); with --arm-neg P, that share
  an arm without its hand: the frame's edge just after a hand left it (`exit_crop`: the
  forearm or whatever was beside the hand, border pixels repeated as the detector repeats
  them, where a track that followed its hand out of the frame stays) and the arm by the
  elbow (`arm_crop` at ELBOW_REACHES), where a false track sat on a bent arm.
Handedness ("does the crop show a right hand as it appears"): a share (--share-left) of
hand crops is presented as a LEFT hand (a right hand mirrored, a left one left as it is);
those train presence and handedness only, every other hand crop is presented as a right
hand and trains all heads. So the keypoint heads see right hands only, and the detector
asks for handedness on the unmirrored crop.
Augmentation (NOTES.md): centre jitter 0.1, scale 0.9-1.1 (real crops, --real-shift and
--real-scale; synthetic crops come jittered), rotation +-90 deg applied to 2D and 3D,
colour jitter, light blur; with
--degrade P a share P of the hand crops also gets a patch of another crop over it, a lower
resolution or sensor noise (`degrade`); with --motion-blur P a share P of the hand crops
is smeared along a line (a hand moving during the exposure) and half of those are also
saved as a low-quality JPEG (a phone's video compression) (`motion_blur`); with
--hand-occluder P a share P of the hand crops gets another person's real hand over part of
it, cut out along its joints (`hand_occluders`: two hands touching or crossing).
"""
import cv2
import numpy as np

from handmocap.perception.crops import CROP, HAND_ANGLES
from handmocap.perception.skeleton import BONES
from handmocap.training import real_data
from handmocap.training.detnet_data import CTX, CTX_CROP_SIDE, HARD_NEGATIVES, WILD_SOURCE


# ------------------------------------------------------------------ batches
def rotate_mirror_3d(xyz, angle_deg, mirror):
    """Root-relative (...,21,3) joints under the crop's in-plane rotation (crop_affine's
    convention, camera x right / y down) and optional mirroring (x -> -x)."""
    a = np.deg2rad(angle_deg)[..., None]
    x, y = xyz[..., 0], xyz[..., 1]
    out = np.stack([np.cos(a) * x + np.sin(a) * y, -np.sin(a) * x + np.cos(a) * y, xyz[..., 2]], -1)
    out[..., 0] *= np.where(np.asarray(mirror)[..., None], -1.0, 1.0)
    return out


class BatchMaker:
    """Numpy batches: image (B,128,128,3) uint8, uv (B,21,2), xyz (B,21,3), w2d, w3d,
    presence, right, w_hand (B,) float32."""

    def __init__(self, synth, real, share_real, share_neg, share_left, upright=None, real_3d=0.0, left_2d=0.0,
                 hard=None, real_scale=(0.9, 1.1), real_shift=0.1, wild_share=None, upright_by="wrist_knuckle"):
        """hard: {kind: (its cache, share)} of HARD_NEGATIVES, each taught as that share of the
        negatives (a cache holds <kind> (m,128,128,3) and <kind>_held (m,) bool). real_scale
        (lo, hi): a real crop's side is the keypoint box x 1.3 x uniform(lo, hi); real_shift:
        its centre moves by up to this share of its side on each axis. wild_share: the share
        of the real crops drawn from the video/wild clips (None: as many as the cache holds).
        upright_by: what "upright" is for `upright` (crops.HAND_ANGLES' names)."""
        self.synth, self.real = synth, real
        # (crops (m,128,128,3), training indices, share) of each hard negative in use
        self.hard = [(pool[kind], np.flatnonzero(~pool[f"{kind}_held"]), share)
                     for kind, (pool, share) in (hard or {}).items()
                     if pool is not None and share > 0 and (~pool[f"{kind}_held"]).any()]
        if sum(share for _, _, share in self.hard) > 1:
            raise ValueError(f"{', '.join(f'--{kind}-neg' for kind in HARD_NEGATIVES)} are shares of the negatives: "
                             "together at most 1")
        self.real_3d = real_3d
        self.left_2d = left_2d
        self.share_left = share_left
        self.upright = upright
        self.hand_angle = HAND_ANGLES[upright_by]
        self.real_scale, self.real_shift = tuple(real_scale), real_shift
        self.real_train = np.flatnonzero(~real["held"]) if real is not None else np.zeros(0, int)
        self.neg_train = np.flatnonzero(~real["neg_held"]) if real is not None else np.zeros(0, int)
        self.share_real = share_real if len(self.real_train) else 0.0
        # the real training crops in two pools, the video/wild clips' and the others', when
        # wild_share says how to mix them (None: one pool)
        self.real_pools, self.wild_share = None, wild_share
        if wild_share is not None and len(self.real_train):
            if "source" not in real:
                raise ValueError("--wild-share needs the real crops' sources, which this data (a device pack?) lacks")
            wild = np.char.startswith(real["source"][self.real_train].astype(str), WILD_SOURCE)
            if not wild.any() or wild.all():
                raise ValueError(f"--wild-share: the real training crops hold {int(wild.sum())} of the video/wild "
                                 f"clips' and {int((~wild).sum())} others; it mixes two non-empty pools")
            self.real_pools = (self.real_train[wild], self.real_train[~wild])
        self.procedural = None
        try:
            from handmocap.training.synth.backgrounds import BackgroundSource
            self.procedural = BackgroundSource(np.random.default_rng(12345), None, 0.0, pool_size=96)
        except Exception as exc:            # the engine is optional for real-data negatives
            print(f"note: no procedural negatives ({exc})")
        self.share_neg = share_neg if len(self.neg_train) or self.procedural is not None else 0.0

    def make(self, n, rng):
        n_neg = int(round(self.share_neg * n))
        n_real = int(round(self.share_real * n))
        n_syn = n - n_neg - n_real
        parts = [self._synth(n_syn, rng)]
        if n_real:
            parts.append(self._real(n_real, rng))
        if n_neg:
            parts.append(self._negatives(n_neg, rng))
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _angles(self, uv, rng):
        """(n,) crop_affine angles, degrees, for hands with 2D joints uv (n,21,2): +-90 about
        the crop as it is, or with `upright` +-upright about the hand turned upright."""
        if self.upright is None:
            return rng.uniform(-90, 90, len(uv))
        return np.degrees(self.hand_angle(uv)) + rng.uniform(-self.upright, self.upright, len(uv))

    def _present(self, n, appears_right, rng):
        """Which crops to show as left hands; mirror flag that makes the rest right hands."""
        show_left = rng.random(n) < self.share_left
        mirror = np.where(show_left, appears_right, ~appears_right)
        return show_left, mirror

    def _side_weight(self, show_left):
        """(n,) handedness-loss weights that give the crops shown as left and as right equal
        shares of the loss, whatever --share-left is."""
        return np.where(show_left, 0.5 / max(self.share_left, 1e-6), 0.5 / max(1 - self.share_left, 1e-6))

    def _synth(self, n, rng):
        s = self.synth
        idx = rng.integers(0, len(s["image"]), n)
        show_left, mirror = self._present(n, s["handedness"][idx] == 0, rng)
        angle = self._angles(s["uv"][idx], rng)
        scale = rng.uniform(0.95, 1.05, n)
        shift = rng.uniform(-0.05, 0.05, (n, 2)) * CROP
        images, uv = np.empty((n, CROP, CROP, 3), np.uint8), np.empty((n, 21, 2), np.float32)
        c = 63.5
        for i in range(n):
            M = real_data.crop_affine(c + shift[i, 0], c + shift[i, 1], CROP * scale[i], CROP, angle[i], mirror[i])
            images[i] = real_data.warp(s["image"][idx[i]], M)
            uv[i] = real_data.apply_affine(M, s["uv"][idx[i]])
        xyz = rotate_mirror_3d(s["xyz_rel"][idx], angle, mirror).astype(np.float32)
        keypoints = (~show_left).astype(np.float32)
        w2d = np.where(show_left, self.left_2d, 1.0).astype(np.float32)
        return {"image": images, "uv": uv, "xyz": xyz, "w2d": w2d, "w3d": keypoints,
                "presence": np.ones(n, np.float32), "right": (~show_left).astype(np.float32),
                "w_hand": self._side_weight(show_left).astype(np.float32)}

    def _real(self, n, rng):
        r = self.real
        if self.real_pools is None:
            idx = self.real_train[rng.integers(0, len(self.real_train), n)]
        else:
            wild, other = self.real_pools
            from_wild = rng.random(n) < self.wild_share
            idx = np.where(from_wild, wild[rng.integers(0, len(wild), n)], other[rng.integers(0, len(other), n)])
        show_left, mirror = self._present(n, r["right"][idx].astype(bool), rng)
        images, uv = np.empty((n, CROP, CROP, 3), np.uint8), np.empty((n, 21, 2), np.float32)
        side0 = CTX_CROP_SIDE                         # the detector's crop side in context px
        angles = np.empty(n)
        for i in range(n):
            side = side0 * rng.uniform(*self.real_scale)
            cx, cy = (CTX - 1) / 2 + rng.uniform(-self.real_shift, self.real_shift, 2) * side
            angles[i] = self._angles(r["uv"][idx[i]][None], rng)[0]
            M = real_data.crop_affine(cx, cy, side, CROP, angles[i], mirror[i])
            images[i] = real_data.warp(r["image"][idx[i]], M)
            uv[i] = real_data.apply_affine(M, r["uv"][idx[i]])
        weight = r["weight"][idx].astype(np.float32)
        keypoints = np.where(show_left, 0.0, weight).astype(np.float32)
        w2d = np.where(show_left, self.left_2d * weight, weight).astype(np.float32)
        xyz, w3d = np.zeros((n, 21, 3), np.float32), np.zeros(n, np.float32)
        if self.real_3d and "has_3d" in r:
            xyz = rotate_mirror_3d(r["xyz"][idx], angles, mirror).astype(np.float32)
            w3d = (keypoints * self.real_3d * r["has_3d"][idx]).astype(np.float32)
        return {"image": images, "uv": uv, "xyz": xyz, "w2d": w2d, "w3d": w3d,
                "presence": np.ones(n, np.float32), "right": (~show_left).astype(np.float32),
                "w_hand": (weight * self._side_weight(show_left)).astype(np.float32)}

    def _negatives(self, n, rng):
        counts = rng.multinomial(n, [share for _, _, share in self.hard] + [1 - sum(s for _, _, s in self.hard)])
        n_other = int(counts[-1])
        n_real = int(rng.binomial(n_other, 0.6)) if len(self.neg_train) else 0
        if self.procedural is None:
            n_real = n_other if len(self.neg_train) else 0
        images = [self.real["neg"][self.neg_train[rng.integers(0, len(self.neg_train), n_real)]]] if n_real else []
        if n_other - n_real:
            images.append(self.procedural.sample(rng, n_other - n_real, CROP)[0])
        for (pool, train, _), k in zip(self.hard, counts):
            if k:
                images.append(pool[train[rng.integers(0, len(train), k)]])
        images = np.concatenate(images)
        for i in np.flatnonzero(rng.random(len(images)) < 0.5):
            images[i] = images[i, :, ::-1]
        zeros = np.zeros(n, np.float32)
        return {"image": images, "uv": np.full((n, 21, 2), -1000.0, np.float32), "xyz": np.zeros((n, 21, 3), np.float32),
                "w2d": np.ones(n, np.float32), "w3d": zeros, "presence": zeros, "right": zeros, "w_hand": zeros}


class IterationBatches:
    """A map-style dataset whose item i is fn(iterations[i]): the batches of a run, for a
    torch DataLoader (batch_size=None) to make in worker processes."""

    def __init__(self, fn, iterations):
        self.fn, self.iterations = fn, list(iterations)

    def __len__(self):
        return len(self.iterations)

    def __getitem__(self, i):
        return self.fn(self.iterations[i])


def degrade(images, hand, share, rng):
    """Degrade a `share` of the crops `images` (B,128,128,3) uint8 where `hand` (B,) bool, in
    place, each one of three ways: a patch (15-45% of the side) of another crop of the batch
    pasted over it (an object, the other hand; its joints stay labelled, as the synthetic
    occluders' do), shrunk to 25-60% and blown up again (a small hand far from the camera),
    or Gaussian noise of 2-8 levels (a dark room's sensor)."""
    for i in np.flatnonzero(hand & (rng.random(len(images)) < share)):
        kind = rng.integers(3)
        if kind == 0:
            side = int(CROP * rng.uniform(0.15, 0.45))
            x, y, sx, sy = rng.integers(0, CROP - side, 4)
            images[i, y:y + side, x:x + side] = images[rng.integers(len(images)), sy:sy + side, sx:sx + side]
        elif kind == 1:
            small = max(8, int(CROP * rng.uniform(0.25, 0.6)))
            images[i] = cv2.resize(cv2.resize(images[i], (small, small), interpolation=cv2.INTER_AREA), (CROP, CROP),
                                   interpolation=cv2.INTER_LINEAR)
        else:
            images[i] = np.clip(images[i] + rng.normal(0, rng.uniform(2, 8), images[i].shape), 0, 255).astype(np.uint8)
    return images


def motion_blur(images, hand, share, rng):
    """Smear a `share` of the crops `images` (B,128,128,3) uint8 where `hand` (B,) bool, in
    place, along a line of 3-15 px at a random angle (a hand moving while the shutter is
    open: the wild clips' fast hands), and save half of those as a JPEG of quality 20-60 (a
    phone's video compression). The line is centred, so the joints' labels stay where they
    are."""
    for i in np.flatnonzero(hand & (rng.random(len(images)) < share)):
        length = int(rng.integers(3, 16))
        kernel = np.zeros((length, length), np.float32)
        kernel[length // 2] = 1.0
        turn = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), rng.uniform(0, 180), 1.0)
        kernel = cv2.warpAffine(kernel, turn, (length, length))
        images[i] = cv2.filter2D(images[i], -1, kernel / kernel.sum(), borderType=cv2.BORDER_REPLICATE)
        if rng.random() < 0.5:
            _, jpg = cv2.imencode(".jpg", images[i], [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(20, 61))])
            images[i] = cv2.imdecode(jpg, cv2.IMREAD_UNCHANGED)
    return images


PALM = (0, 1, 5, 9, 13, 17)      # joints whose polygon is the palm (MP order)


def hand_mask(uv, size=CROP, forearm=True):
    """Soft silhouette (size,size) float32 in [0, 1] of a hand drawn from its 2D joints uv
    (21,2) crop px: the palm's polygon, each bone as a line 0.09 x the hand's size thick
    (skeleton.BONES), and (forearm) the forearm as a thick line from the wrist away from
    the middle finger's knuckle; edges feathered over about 3 px."""
    hand = float(real_data.hand_size(uv))
    mask = np.zeros((size, size), np.uint8)
    pts = lambda a: np.round(a * 16).astype(np.int32)                      # noqa: E731  (4 fractional bits)
    cv2.fillPoly(mask, [pts(uv[list(PALM)])], 255, cv2.LINE_AA, shift=4)
    for a, b in BONES:
        cv2.line(mask, tuple(pts(uv[a])), tuple(pts(uv[b])), 255, max(1, int(0.09 * hand)), cv2.LINE_AA, shift=4)
    if forearm:
        away = uv[0] - uv[9]
        elbow = uv[0] + away / max(np.linalg.norm(away), 1e-6) * 0.8 * hand
        cv2.line(mask, tuple(pts(uv[0])), tuple(pts(elbow)), 255, max(1, int(0.28 * hand)), cv2.LINE_AA, shift=4)
    return cv2.GaussianBlur(mask, (0, 0), 1.2).astype(np.float32) / 255.0


def hand_occluders(images, uv, hand, share, rng, real, pool):
    """Put another person's real hand over a `share` of the crops `images` (B,128,128,3)
    uint8 where `hand` (B,) bool, in place: two hands touching, clasped or crossing (the
    wild clips' signers and hand washers), which the rendered second hands do not show
    with real skin. The occluder is a hand of the real training crops (real["image"] the
    context crops, real["uv"] their joints; pool: their indices), turned, mirrored and
    sized 0.7-1.3x the crop's own hand (uv (B,21,2) crop px), centred 0.5-0.9 of the
    hand's size from the hand's centre, cut out with hand_mask. The crop's own joints stay
    labelled where they are, as under the rendered occluders."""
    for i in np.flatnonzero(hand & (rng.random(len(images)) < share)):
        j = pool[rng.integers(len(pool))]
        *own_centre, own = real_data.crop_box(uv[i], scale=1.0)          # the joint boxes' centres and sides
        *src_centre, theirs = real_data.crop_box(real["uv"][j], scale=1.0)
        direction = rng.uniform(0, 2 * np.pi)
        centre = np.array(own_centre) + rng.uniform(0.5, 0.9) * own * np.array([np.cos(direction), np.sin(direction)])
        # the occluder's joint box centre goes to `centre`, its size to own x 0.7-1.3
        scale = own * rng.uniform(0.7, 1.3) / max(theirs, 1.0)
        src_centre = np.array(src_centre)
        M = cv2.getRotationMatrix2D(tuple(float(v) for v in src_centre), rng.uniform(0, 360), scale)
        M[:, 2] += centre - src_centre
        if rng.random() < 0.5:                      # mirrored about the new centre: the other side
            M = np.array([[-1.0, 0, 2 * centre[0]], [0, 1.0, 0]]) @ np.vstack([M, [0, 0, 1]])
        occ = cv2.warpAffine(real["image"][j], M, (CROP, CROP), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        occ_uv = real["uv"][j] @ M[:, :2].T + M[:, 2]
        alpha = hand_mask(occ_uv)[..., None]
        images[i] = (images[i] * (1.0 - alpha) + occ * alpha + 0.5).astype(np.uint8)
    return images


def to_torch(batch, rng=None, grey=0.0):
    """Tensors; images (B,3,128,128) float [0,1], with colour jitter and light blur when rng,
    and that share `grey` of them in grey (three equal channels: a mono or IR camera)."""
    import torch
    t = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in batch.items()}
    img = t["image"].permute(0, 3, 1, 2).float() / 255.0
    if rng is not None:
        n = img.shape[0]
        r = lambda lo, hi, *shape: torch.from_numpy(rng.uniform(lo, hi, (n, *shape)).astype(np.float32))  # noqa: E731
        mono = img.mean(1, keepdim=True)
        img = mono + (img - mono) * r(0.5, 1.5, 1, 1, 1)                          # saturation
        mean = img.mean((1, 2, 3), keepdim=True)
        img = mean + (img - mean) * r(0.6, 1.4, 1, 1, 1)                          # contrast
        img = img * r(0.6, 1.4, 1, 1, 1) * r(0.85, 1.15, 3, 1, 1)                 # brightness, white balance
        blur = torch.from_numpy(rng.random(n) < 0.3)
        if blur.any():
            k = torch.tensor([0.25, 0.5, 0.25])
            k2 = (k[:, None] * k[None, :]).expand(3, 1, 3, 3)
            img[blur] = torch.nn.functional.conv2d(torch.nn.functional.pad(img[blur], (1, 1, 1, 1), mode="replicate"),
                                                   k2, groups=3)
        img = img.clamp(0.0, 1.0)
        if grey:
            luma = (img * torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)).sum(1, keepdim=True)
            img = torch.where(torch.from_numpy(rng.random(n) < grey).view(n, 1, 1, 1), luma.expand_as(img), img)
    t["image"] = img.contiguous()
    return t
