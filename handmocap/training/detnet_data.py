"""DetNet's training data: the synthetic shards (`handsynth`) and the real crops cut once
from the data pack into caches under DATA_DIR (`load_real`: hands with MediaPipe's 2D labels,
the held-back people's for validation only; `load_parts`, `load_arms`, `load_near`: the hard
negatives). What each holds and how it is cut: the builders' docstrings. Batches are made from
these by detnet_batches.BatchMaker.
"""
import glob
import os
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.skeleton import normalize_joints
from handmocap.training import real_data
from handmocap.perception.crops import CROP


DATA_DIR = Path("runs/detnet_data")
CTX = 176                    # real hand context crops: px, covering CTX_SCALE x the keypoint box
CTX_SCALE = 2.4
CTX_CROP_SIDE = (CTX - 1) / CTX_SCALE * 1.3   # context px: the detector's crop (the keypoint box x 1.3) in a context crop
REAL_CACHE = "real_v5.npz"          # v2: + arm-only negatives; v3: frame edges repeated as the detector repeats them;
                                    # v4: + MediaPipe world landmarks of the video hands (xyz, has_3d);
                                    # v5: + video/wild, 11K Hands, images/scenes; pseudo-labels filtered
                                    # (real_data.reliable_hands); the held-back people, validation only
DROP_CACHES = {"wild3": "wild3_v1.npz"}    # the later drops of people's own clips: video/<drop> -> its cache (build_drop_cache)
HELD_BACK_SOURCE = "heldback/"      # source prefix of the held-back people's crops (never trained on)
WILD_SOURCE = "wild/"              # source prefix of the training people's video/wild crops (--wild-share)
PART_CACHE = "parts_v1.npz"         # close-ups of part of a hand (build_part_cache), negatives for --part-neg
ARM_CACHE = "arms_v1.npz"           # an arm without its hand (build_arm_cache), negatives for --arm-neg
NEAR_CACHE = "near_v1.npz"          # the scene just beside a hand (build_near_cache), negatives for --near-neg
FACE_CACHE = "faces_v2.npz"         # a face with no hand in the crop (build_face_cache), negatives for --face-neg
ELBOW_REACHES = (1.6, 2.0, 2.4)     # arm_crop reaches (crop sides beyond the wrist) by the elbow


# ------------------------------------------------------------------ synthetic data
def synth_dirs(patterns):
    """Complete shard directories (meta.json written last by handsynth) matching the globs."""
    return sorted({d for pat in patterns for d in glob.glob(pat) if (Path(d) / "meta.json").exists()})


def load_synth(dirs, limit):
    """Concatenated arrays image (n,128,128,3) uint8, uv (n,21,2), xyz_rel (n,21,3), xyz
    (n,21,3) m, handedness (n,) int8 (0 right), in_image (n,21) of the shard dirs."""
    from handmocap.training.synth.dataset import SynthDataset
    keys = ("image", "uv", "xyz_rel", "xyz", "handedness", "in_image")
    parts = {k: [] for k in keys}
    total = 0
    for d in dirs:
        ds = SynthDataset(d)
        for k in range(len(ds.counts)):
            if total >= limit:
                break
            shard = ds.shard(k)
            for key in keys:
                parts[key].append(shard[key])
            total += len(shard["image"])
    return {k: np.concatenate(v)[:limit] for k, v in parts.items()} if total else None


# ------------------------------------------------------------------ real data
def _boxes_overlap(box, boxes):
    return any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3] for b in boxes)


class RealCutter:
    """Cuts real hands into context crops (CTX px around the keypoint box x CTX_SCALE) and
    negatives beside them, collecting the arrays a real cache holds (`save`):

    Hands: image (n,CTX,CTX,3), uv (n,21,2) in context px, right (n,) 1 if the hand appears
    as a right hand, weight (n,) label weight, held (n,) bool held-out, source (n,) str,
    xyz (n,21,3) MediaPipe's world landmarks made root-relative and scale-normalized (joint
    ROOT at 0, |j0 - j_ROOT| = 1; frame camera axes, the hand as it appears) and has_3d (n,)
    bool where there are any (the videos; howiema has 2D only).
    Negatives: neg (m,128,128,3) uint8, neg_held (m,) bool held-out, neg_arm (m,) bool an
    arm-only crop (`arm_crop`).
    """

    def __init__(self, rng, log=print):
        self.rng, self.log = rng, log
        self.hands = {k: [] for k in ("image", "uv", "right", "weight", "held", "source", "xyz", "has_3d")}
        self.negs, self.neg_held, self.neg_arm = [], [], []

    def add_hand(self, image, uv, right, weight, held, source, world=None):
        cx, cy, side = real_data.crop_box(uv, CTX_SCALE)
        if side < 16:
            return
        M = real_data.crop_affine(cx, cy, side, CTX)
        self.hands["image"].append(real_data.warp(image, M, CTX, replicate=True))
        self.hands["uv"].append(real_data.apply_affine(M, uv).astype(np.float32))
        xyz = None if world is None else normalize_joints(world)
        has_3d = xyz is not None and bool(np.all(np.isfinite(xyz)))
        for k, v in (("right", right), ("weight", weight), ("held", held), ("source", source),
                     ("xyz", xyz.astype(np.float32) if has_3d else np.zeros((21, 3), np.float32)),
                     ("has_3d", has_3d)):
            self.hands[k].append(v)

    def add_negative(self, crop, held, arm):
        self.negs.append(crop)
        self.neg_held.append(bool(held))
        self.neg_arm.append(bool(arm))

    def add_video(self, video, split=real_data.video_split, stride=1, source=None, negatives=True):
        """The reliable pseudo-labelled hands (real_data.reliable_hands) of every `stride`-th
        frame where train | held ((F,) bool each, split(F)), and negatives beside them on
        every 3rd."""
        rng = self.rng
        lab = real_data.load_pseudo_labels(video)
        train, held = split(len(lab["found"]))
        reliable = real_data.reliable_hands(lab)
        keep = {f for f in range(0, len(lab["found"]), stride) if train[f] or held[f]}
        for f, image in real_data.read_video(video, keep):
            if f >= len(lab["found"]):
                continue
            slots = np.flatnonzero(lab["found"][f])
            boxes = [np.r_[lab["uv"][f, s].min(0), lab["uv"][f, s].max(0)] for s in slots]
            for s in np.flatnonzero(reliable[f]):
                self.add_hand(image, lab["uv"][f, s], lab["handedness"][f, s] == 0, float(lab["score"][f, s]),
                              bool(held[f]), source or video.stem, lab["world"][f, s])
            if negatives and len(slots) and f % 3 == 0:    # negatives: squares of hand-like size, away from hands
                h, w = image.shape[:2]
                grown = [np.r_[b[:2] - 0.3 * (b[2:] - b[:2]) - 12, b[2:] + 0.3 * (b[2:] - b[:2]) + 12] for b in boxes]
                base = max(max(b[2] - b[0], b[3] - b[1]) for b in boxes) * 1.3
                for _ in range(4):
                    side = float(np.clip(base * rng.uniform(0.6, 1.6), 32, min(h, w)))
                    x0, y0 = rng.uniform(0, w - side), rng.uniform(0, h - side)
                    if not _boxes_overlap((x0, y0, x0 + side, y0 + side), grown):
                        M = real_data.crop_affine(x0 + side / 2, y0 + side / 2, side, CROP)
                        self.add_negative(real_data.warp(image, M, CROP, replicate=True), held[f], False)
                        break
                for k, s in enumerate(slots):         # arm-only negatives: a tracked crop that slid up the forearm
                    arm = arm_crop(lab["uv"][f, s], rng)
                    if arm is None:
                        continue
                    box, others = arm_box(arm), [g for j, g in enumerate(grown) if j != k]
                    if not _boxes_overlap(box, others) and _inside_share(box, w, h) >= 0.8:   # mostly inside the frame: not a streak of repeated edge pixels
                        self.add_negative(real_data.warp(image, arm, CROP, replicate=True), held[f], True)
        self.log(f"  {video.name}: {len(self.hands['image'])} hands, {len(self.negs)} negatives so far")

    def add_drop(self, shared, drop, held_back):
        """The clips of one drop of people's own clips (video/<drop>), all training or all held
        out: every 2nd frame of the training people's clips (source WILD_SOURCE + clip, with
        negatives), every 3rd of the held-back people's (validation only: source
        HELD_BACK_SOURCE + clip for the second drop, + "<drop>/" + clip for later drops)."""
        def whole(n):           # a clip is all training or all held out
            return np.full(n, not held_back), np.full(n, held_back)
        for video in real_data.wild_clips(shared, held_back, drops=(drop,)):
            named = video.stem if drop == "wild" else f"{drop}/{video.stem}"
            self.add_video(video, whole, stride=3 if held_back else 2,
                           source=HELD_BACK_SOURCE + named if held_back else WILD_SOURCE + video.stem,
                           negatives=not held_back)

    def save(self, path):
        """The arrays cut so far, written to `path` (write_npz) and returned."""
        arrays = {k: np.asarray(v) for k, v in self.hands.items()}
        arrays["neg"] = np.asarray(self.negs, np.uint8).reshape(-1, CROP, CROP, 3)
        arrays["neg_held"], arrays["neg_arm"] = np.asarray(self.neg_held, bool), np.asarray(self.neg_arm, bool)
        write_npz(path, arrays)
        return arrays


def build_real_cache(shared, path, seed=0, log=print):
    """Cut every usable real hand of the pack but the later drops' clips (howiema 001, the
    training videos, video/wild, 11K Hands, images/scenes) into context crops, with a few
    negatives per video frame (RealCutter); save the arrays to `path`."""
    cut = RealCutter(np.random.default_rng([seed, 99]), log)
    for seq in real_data.load_howiema(real_data.HOWIEMA_TRAIN_SUBJECT, shared):
        seq_name = seq["name"].split("/")[1]
        cut.add_hand(seq["image"], seq["uv"], seq["handedness"] == "right", 1.0, seq_name in real_data.HOWIEMA_HELD_OUT,
                     "howiema001/" + seq_name)
    for rel in real_data.TRAIN_VIDEOS:
        cut.add_video(Path(shared) / rel)
    # many more people (the pack's second drop), and 11K Hands' photos of people
    for held_back in (False, True):
        cut.add_drop(shared, "wild", held_back)
        for s in real_data.load_11khands(shared, held_back):
            cut.add_hand(s["image"], s["uv"], s["handedness"] == "right", 1.0, held_back,
                         (HELD_BACK_SOURCE if held_back else "") + "11k/" + s["name"].split("/")[0])
        log(f"  11K Hands ({'held back' if held_back else 'training'} people): {len(cut.hands['image'])} hands so far")
    for s in real_data.load_scenes(shared):
        cut.add_hand(s["image"], s["uv"], s["handedness"] == "right", 1.0, False, "scenes")
    log(f"  images/scenes: {len(cut.hands['image'])} hands")
    return cut.save(path)


def build_drop_cache(shared, path, drop, seed=0, log=print):
    """A later drop's clips (video/<drop>: its training people and, for validation only, its
    held-back people; RealCutter.add_drop) cut as the real cache cuts video/wild's, saved to
    `path`: a new drop adds a cache of its own rather than re-cutting the others."""
    cut = RealCutter(np.random.default_rng([seed, 99, len(drop)]), log)
    for held_back in (False, True):
        cut.add_drop(shared, drop, held_back)
    return cut.save(path)


def jittered_side(uv, rng, scale=1.3):
    """The side (px) of a crop of the hand with keypoints uv (21,2) as the detector cuts it
    (keypoint box x `scale`), x 0.8-1.2 at random: the hard negatives' crop size."""
    return float(np.max(uv.max(0) - uv.min(0))) * scale * rng.uniform(0.8, 1.2)


def grown_box(uv, share=0.3):
    """(4,) x0, y0, x1, y1: the box of keypoints uv (k,2) grown by `share` of its size each way."""
    return np.r_[uv.min(0) - share * np.ptp(uv, 0), uv.max(0) + share * np.ptp(uv, 0)]


def arm_crop(uv, rng, scale=1.3, reaches=(0.7, 0.85, 1.0, 1.2)):
    """The (2,3) affine of a 128 px crop of the forearm beside a hand with keypoints uv
    (21,2): the hand's crop side (keypoint box x `scale`, x 0.8-1.2), centred beyond the
    wrist along middle MCP -> wrist, at the first of `reaches` (crop sides from the wrist;
    ELBOW_REACHES: further up the arm, by the elbow) where no keypoint is inside it; None
    for a degenerate hand. The forearm may be out of the frame (the warp repeats its border)."""
    side = jittered_side(uv, rng, scale)
    d = uv[0] - uv[9]
    if side < 16 or np.linalg.norm(d) < 1e-3:
        return None
    d = d / np.linalg.norm(d)
    for reach in reaches:                     # crop edge beyond the wrist, in crop sides
        c = uv[0] + d * side * (reach + rng.uniform(-0.05, 0.1))
        if not np.any(np.all(np.abs(uv - c) < side / 2 * 1.25, axis=1)):   # margin: the crop turns by up to 30 deg
            return real_data.crop_affine(c[0], c[1], side, CROP, angle_deg=rng.uniform(-30, 30))
    return None


def arm_box(M, size=CROP):
    """(4,) x0 y0 x1 y1 image px bounding the crop of the (2,3) affine M (image -> crop)."""
    inv = cv2.invertAffineTransform(M)
    corners = np.array([[0, 0], [size, 0], [0, size], [size, size]], float) @ inv[:, :2].T + inv[:, 2]
    return np.r_[corners.min(0), corners.max(0)]


def part_crop(uv, rng, scale=1.3, min_side=40.0):
    """The (2,3) affine of a 128 px close-up of part of a hand with keypoints uv (21,2): a
    square 0.25-0.5 of the hand's crop side (keypoint box x `scale`) around a joint other
    than the wrist, turned at random. It is what DetNet is shown when the finder's box is
    on a fingertip or the knuckles of a hand that fills a photo, where it read a tiny hand.
    None where that square would be under `min_side` frame px (blown up to 128 px it would
    be a blur, which tiny far-away hands are too)."""
    side = float(np.max(uv.max(0) - uv.min(0))) * scale * rng.uniform(0.25, 0.5)
    if side < min_side:
        return None
    c = uv[rng.integers(1, 21)] + rng.uniform(-0.25, 0.25, 2) * side
    return real_data.crop_affine(c[0], c[1], side, CROP, angle_deg=rng.uniform(-180, 180))


def build_part_cache(shared, path, seed=0, log=print):
    """Close-ups of part of a hand (`part_crop`) cut from the training videos' full frames,
    one per labelled hand on every 3rd frame, and from howiema subject 001: part
    (m,128,128,3) uint8, part_held (m,) bool (the frames the real cache holds out)."""
    rng = np.random.default_rng([seed, 7])
    parts, held_out = [], []

    def add(image, uv, held):
        M = part_crop(uv, rng)
        if M is not None:
            parts.append(real_data.warp(image, M, CROP, replicate=True))
            held_out.append(held)

    for seq in real_data.load_howiema(real_data.HOWIEMA_TRAIN_SUBJECT, shared):
        add(seq["image"], seq["uv"], seq["name"].split("/")[1] in real_data.HOWIEMA_HELD_OUT)
    for rel in real_data.TRAIN_VIDEOS:
        video = Path(shared) / rel
        lab = real_data.load_pseudo_labels(video)
        train, held = real_data.video_split(len(lab["found"]))
        for f, image in real_data.read_video(video, frames=set(range(0, len(lab["found"]), 3))):
            if f < len(lab["found"]) and (train[f] or held[f]):
                for s in np.flatnonzero(lab["found"][f]):
                    add(image, lab["uv"][f, s], bool(held[f]))
        log(f"  {rel}: {len(parts)} part-of-hand close-ups so far")
    return _save_crops(path, "part", parts, held_out)


def _save_crops(path, kind, crops, held_out):
    """{kind: (m,128,128,3) uint8, kind_held: (m,) bool}, also written to the .npz `path`."""
    arrays = {kind: np.asarray(crops, np.uint8).reshape(-1, CROP, CROP, 3), f"{kind}_held": np.asarray(held_out, bool)}
    write_npz(path, arrays)
    return arrays


def write_npz(path, arrays):
    """np.savez to `path` through a temporary file in the same folder and a rename, so two
    runs building the same cache at once (or one stopped half-way) never leave a torn file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def _crop_cache(shared, name, build, what, log):
    """A hard-negative cache (built by build(shared, path) on first use under runs/detnet_data/),
    or None without shared/."""
    if not (Path(shared) / "labelled2d").exists():
        return None
    return _cached(DATA_DIR / name, lambda path: build(shared, path, log=log), f"cutting {what} from {shared}", log)


def load_parts(shared, log=print):
    """The part-of-hand cache (build_part_cache)."""
    return _crop_cache(shared, PART_CACHE, build_part_cache, "part-of-hand close-ups", log)


def exit_crop(image, uv, rng, others=(), scale=1.3):
    """A 128 px crop of the frame's edge just after the hand with keypoints uv (21,2) left it,
    or None. The frame `image` (H,W,3) is cut along the axis nearest the hand's direction
    (wrist -> middle knuckle) so that the hand lies wholly beyond the cut; the crop (the
    hand's crop side x 0.8-1.2, turned at random) is centred from a fifth of its side beyond
    that new edge to half of it inside, by the wrist (+-a quarter side), with the border
    pixels repeated as the detector repeats them: the forearm, or whatever was beside the
    hand, where a track that followed its hand out of the frame is left. None where the cut
    frame is narrower than the crop or one of `others` (other hands' keypoints) is in it."""
    side = jittered_side(uv, rng, scale)
    way = uv[9] - uv[0]
    if side < 16 or not np.all(np.isfinite(uv)) or np.linalg.norm(way) < 1e-3:
        return None
    axis = int(abs(way[1]) > abs(way[0]))                  # 0: x (left / right edge), 1: y (top / bottom)
    length = image.shape[1 - axis]
    margin = 0.05 * side
    if way[axis] > 0:           # the hand left through the far edge: the frame ends before it
        lo, hi = 0, int(np.floor(uv[:, axis].min() - margin))
        edge, inward = hi - lo, -1.0
    else:
        lo, hi = int(np.ceil(uv[:, axis].max() + margin)), length
        edge, inward = 0.0, 1.0
    if hi - lo < side:
        return None
    centre = np.empty(2)
    centre[axis] = edge + inward * side * rng.uniform(-0.2, 0.5)
    centre[1 - axis] = uv[0, 1 - axis] + rng.uniform(-0.25, 0.25) * side
    shift = np.zeros(2)
    shift[axis] = lo                                       # frame px -> cut-frame px
    M = real_data.crop_affine(centre[0], centre[1], side, CROP, angle_deg=rng.uniform(-180, 180))
    for other in others:
        if np.any(np.all(np.abs(real_data.apply_affine(M, other - shift) - 63.5) < 80, axis=1)):
            return None
    kept = image[:, lo:hi] if axis == 0 else image[lo:hi]
    return real_data.warp(np.ascontiguousarray(kept), M, CROP, replicate=True)


def for_training_frames(shared, add_frame, progress, every_found_reliable=False, drops=("wild",)):
    """add_frame(image (H,W,3) RGB, hands (k,21,2) reliable pseudo-labelled keypoints, held)
    for every 2nd frame of the training videos (held: their held-out tails), every 3rd of the
    training clips of the `drops` (video/wild by default) and every images/scenes photo;
    progress(name) after each source. every_found_reliable: only frames whose every hand
    MediaPipe found is reliable. Never the held-back people."""
    videos = [(Path(shared) / rel, real_data.video_split, 2) for rel in real_data.TRAIN_VIDEOS]
    videos += [(v, lambda n: (np.ones(n, bool), np.zeros(n, bool)), 3) for v in real_data.wild_clips(shared, drops=drops)]
    for video, split, stride in videos:
        lab = real_data.load_pseudo_labels(video)
        train, held = split(len(lab["found"]))
        reliable = real_data.reliable_hands(lab)
        for f, image in real_data.read_video(video, frames=set(range(0, len(lab["found"]), stride))):
            if f >= len(lab["found"]) or not (train[f] or held[f]) or not reliable[f].any():
                continue
            if not every_found_reliable or np.array_equal(reliable[f], lab["found"][f]):
                add_frame(image, lab["uv"][f][reliable[f]], bool(held[f]))
        progress(video.name)
    scenes = {}
    for s in real_data.load_scenes(shared):          # a photo with two hands is two samples
        scenes.setdefault(s["name"], (s["image"], []))[1].append(s["uv"])
    for image, hands in scenes.values():
        add_frame(image, np.asarray(hands), False)
    progress("images/scenes")


def build_arm_cache(shared, path, seed=0, log=print):
    """Crops of an arm without its hand, from each reliable pseudo-labelled hand on every 2nd
    frame of the training videos, every 3rd of the training clips of video/wild and every
    images/scenes photo: the frame's edge after the hand left (`exit_crop`) and the arm by
    the elbow (`arm_crop` at ELBOW_REACHES, mostly inside the frame, no other hand in it).
    arm (m,128,128,3) uint8, arm_held (m,) bool (the training videos' held-out tails).
    Never from the held-back people."""
    rng = np.random.default_rng([seed, 11])
    crops, held_out = [], []

    def add_frame(image, hands, held):
        h, w = image.shape[:2]
        for k, uv in enumerate(hands):
            others = [o for j, o in enumerate(hands) if j != k]
            crop = exit_crop(image, uv, rng, others)
            elbow = arm_crop(uv, rng, reaches=ELBOW_REACHES)
            if elbow is not None:
                box = arm_box(elbow)
                if _boxes_overlap(box, [grown_box(o) for o in others]) or _inside_share(box, w, h) < 0.6:
                    elbow = None
            for c in (crop, None if elbow is None else real_data.warp(image, elbow, CROP, replicate=True)):
                if c is not None:
                    crops.append(c)
                    held_out.append(held)

    for_training_frames(shared, add_frame, lambda where: log(f"  {where}: {len(crops)} arm crops so far"))
    return _save_crops(path, "arm", crops, held_out)


def near_crop(image, uv, rng, others=(), scale=1.3):
    """A 128 px crop of the scene just beside the hand with keypoints uv (21,2), or None: the
    hand's crop side x 0.8-1.2, centred 0.9-1.6 sides from the hand's box centre in a random
    direction, where a track that lost its hand drifts (hair, a face, clothes). None where it
    overlaps this hand's or one of `others`' boxes grown by 30%, or is under 80% inside the frame."""
    side = jittered_side(uv, rng, scale)
    if side < 16 or not np.all(np.isfinite(uv)):
        return None
    way = rng.uniform(0, 2 * np.pi)
    cx, cy = (uv.min(0) + uv.max(0)) / 2 + rng.uniform(0.9, 1.6) * side * np.array([np.cos(way), np.sin(way)])
    box = (cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2)
    h, w = image.shape[:2]
    if _boxes_overlap(box, [grown_box(o) for o in (uv, *others)]) or _inside_share(box, w, h) < 0.8:
        return None
    return real_data.warp(image, real_data.crop_affine(cx, cy, side, CROP, angle_deg=rng.uniform(-30, 30)), CROP,
                          replicate=True)


def build_near_cache(shared, path, seed=0, log=print):
    """Crops of the scene beside each reliable pseudo-labelled hand (`near_crop`, two tries a
    hand) on every 2nd frame of the training videos where MediaPipe found a hand, every 3rd
    of the training clips of video/wild and every images/scenes photo: near (m,128,128,3)
    uint8, near_held (m,) bool (the training videos' held-out tails). Frames where MediaPipe
    found fewer hands than are there would give a crop of a hand: only frames whose every
    found hand is reliable are used. Never from the held-back people."""
    rng = np.random.default_rng([seed, 12])
    crops, held_out = [], []

    def add_frame(image, hands, held):
        for k, uv in enumerate(hands):
            for _ in range(2):
                crop = near_crop(image, uv, rng, [o for j, o in enumerate(hands) if j != k])
                if crop is not None:
                    crops.append(crop)
                    held_out.append(held)
                    break

    for_training_frames(shared, add_frame, lambda where: log(f"  {where}: {len(crops)} crops beside a hand so far"),
                        every_found_reliable=True)
    return _save_crops(path, "near", crops, held_out)


def face_boxes(image, max_side=480):
    """(k,4) x0, y0, x1, y1 frame px of the frontal faces OpenCV's stock Haar cascade
    (`haarcascade_frontalface_default.xml`, shipped in the opencv wheel) finds in the RGB
    frame `image` (H,W,3), read at most `max_side` px on its longer side."""
    cascade = face_boxes.__dict__.get("cascade")
    if cascade is None:
        cascade = face_boxes.cascade = cv2.CascadeClassifier(cv2.data.haarcascades + "haarcascade_frontalface_default.xml")
    zoom = min(1.0, max_side / max(image.shape[:2]))
    gray = cv2.cvtColor(cv2.resize(image, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_AREA) if zoom < 1 else image,
                        cv2.COLOR_RGB2GRAY)
    found = cascade.detectMultiScale(gray, scaleFactor=1.1, minNeighbors=6, minSize=(24, 24))
    boxes = np.asarray(found, float).reshape(-1, 4) / zoom
    return np.c_[boxes[:, :2], boxes[:, :2] + boxes[:, 2:]]


def face_crop(image, face, hands, rng, scale=1.3, margin=8):
    """A 128 px crop of the face `face` (4,) x0 y0 x1 y1, or None: the side of a crop of one
    of the frame's hands `hands` (k,21,2) as the detector cuts it (x 0.8-1.2), centred within
    a quarter of the face's size of its centre, turned at random (a track's crop turns with
    the hand it followed): where a track that lost its hand by the face sits. A hand may be
    just beside the crop (a hand held below the face: where session 59's false track was
    born), none of its keypoints within `margin` crop px of it. None where one is, or where
    the crop is under 80% inside the frame."""
    side = jittered_side(hands[rng.integers(len(hands))], rng, scale)
    size = face[2:] - face[:2]
    cx, cy = (face[:2] + face[2:]) / 2 + rng.uniform(-0.25, 0.25, 2) * size
    box = (cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2)
    h, w = image.shape[:2]
    if side < 16 or _inside_share(box, w, h) < 0.8:
        return None
    M = real_data.crop_affine(cx, cy, side, CROP, angle_deg=rng.uniform(-180, 180))
    half = (CROP - 1) / 2
    for uv in hands:
        if np.any(np.all(np.abs(real_data.apply_affine(M, uv) - half) < half + margin, axis=1)):
            return None
    return real_data.warp(image, M, CROP, replicate=True)


def build_face_cache(shared, path, seed=0, log=print):
    """Crops of each face (`face_boxes`) with no hand in the crop (`face_crop`, three tries a
    face) on the frames `for_training_frames` gives (both drops' training clips: the signers
    of video/wild3 show most of the faces), only frames whose every found hand is reliable.
    Saved: face (m,128,128,3) uint8, face_held (m,) bool (the training videos' held-out tails).
    A face is the scene's most hand-like patch (skin, a hand-sized blob) and where tracks
    wrongly born stay. Never from the held-back people."""
    rng = np.random.default_rng([seed, 13])
    crops, held_out = [], []

    def add_frame(image, hands, held):
        for face in face_boxes(image):
            for _ in range(3):
                crop = face_crop(image, face, hands, rng)
                if crop is not None:
                    crops.append(crop)
                    held_out.append(held)
                    break

    for_training_frames(shared, add_frame, lambda where: log(f"  {where}: {len(crops)} face crops so far"),
                        every_found_reliable=True, drops=real_data.WILD_DROPS)
    return _save_crops(path, "face", crops, held_out)


def load_faces(shared, log=print):
    """The face cache (build_face_cache)."""
    return _crop_cache(shared, FACE_CACHE, build_face_cache, "face crops", log)


def load_near(shared, log=print):
    """The beside-a-hand cache (build_near_cache)."""
    return _crop_cache(shared, NEAR_CACHE, build_near_cache, "crops beside a hand", log)


def load_arms(shared, log=print):
    """The arm-without-its-hand cache (build_arm_cache)."""
    return _crop_cache(shared, ARM_CACHE, build_arm_cache, "arm crops", log)


# the hard negatives, each taught as that share (--<kind>-neg) of the no-hand crops:
# kind -> (its cache's loader, what it shows)
HARD_NEGATIVES = {"part": (load_parts, "part-of-hand close-ups"),
                  "arm": (load_arms, "arm crops (edge of frame, elbow)"),
                  "near": (load_near, "crops beside a hand"),
                  "face": (load_faces, "face crops")}


def _cached(path, build, what, log):
    """The arrays of the .npz at `path`, or those build(path) writes there (once)."""
    if path.exists():
        with np.load(path) as data:
            return {k: data[k] for k in data.files}
    log(f"{what} into {path} (once)")
    return build(path)


def _inside_share(box, w, h):
    """Share of box (4,) x0 y0 x1 y1 inside a w x h image."""
    ix = max(0.0, min(box[2], w) - max(box[0], 0.0))
    iy = max(0.0, min(box[3], h) - max(box[1], 0.0))
    return ix * iy / max((box[2] - box[0]) * (box[3] - box[1]), 1e-9)


def load_real(shared, log=print):
    """The real crops (RealCutter's arrays): the real cache and each later drop's cache
    (DROP_CACHES), built on first use under runs/detnet_data/ and concatenated; None without
    shared/."""
    if not (Path(shared) / "labelled2d").exists():
        log(f"note: no real data pack at {shared}; training on synthetic data only")
        return None
    parts = [_cached(DATA_DIR / REAL_CACHE, lambda path: build_real_cache(shared, path, log=log),
                     f"cutting real crops from {shared}", log)]
    for drop, name in DROP_CACHES.items():
        if (Path(shared) / "video" / drop).is_dir():
            parts.append(_cached(DATA_DIR / name, lambda path: build_drop_cache(shared, path, drop, log=log),
                                 f"cutting video/{drop}'s crops from {shared}", log))
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
