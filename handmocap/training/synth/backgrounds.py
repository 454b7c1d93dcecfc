"""Backgrounds: crops of real video frames that contain no hand, and procedural textures.

Real crops come from the videos in shared/data/video/ (never `temugeb_stereo`, which is
kept for evaluation). Each video's `<stem>.mediapipe.npz` gives hand pixels per frame;
a frame is used only where MediaPipe found a hand (a frame without detections may hide
a missed hand), and a crop is kept only if it overlaps no hand box of any frame within
+-10 frames (boxes grown by 30% plus 12 px). The crops are cut at run time into a
git-ignored cache (HANDMOCAP_CACHE, default <repo>/.cache/synth) — never committed.
Without shared/ (a user's clone) the engine uses procedural backgrounds only: fractal
noise, gradients, stripes and checkers, indoor-like blocks, and random shapes, some of
them skin-coloured (hard negatives).
"""
import json
import os
from pathlib import Path

import cv2
import numpy as np

from .appearance import SKIN_TONES, random_hsv_colours

REPO = Path(__file__).resolve().parents[3]
EXCLUDED_VIDEOS = ("temugeb_stereo",)
CACHE_VERSION = 1
CROP_SIZE = 160


def shared_data_dir():
    """shared/data beside the repository (or HANDMOCAP_SHARED_DATA), None if absent."""
    env = os.environ.get("HANDMOCAP_SHARED_DATA")
    path = Path(env) if env else REPO.parent / "shared" / "data"
    return path if (path / "video").is_dir() else None


def cache_dir():
    return Path(os.environ.get("HANDMOCAP_CACHE", REPO / ".cache" / "synth"))


def _hand_boxes(npz_path, grow=0.3, pad=12.0):
    """Per frame (F,) list of (k,4) hand boxes x0,y0,x1,y1 and found (F,) bool."""
    d = np.load(npz_path)
    uv, found = d["uv"], d["found"]                     # (F,2,21,2), (F,2)
    lo, hi = uv.min(2), uv.max(2)                       # (F,2,2)
    size = hi - lo
    lo, hi = lo - size * grow - pad, hi + size * grow + pad
    box = np.concatenate([lo, hi], -1)                  # (F,2,4)
    return [box[i][found[i]] for i in range(len(found))], found.any(1)


def _overlaps(box, boxes):
    if len(boxes) == 0:
        return False
    return bool(np.any((box[0] < boxes[:, 2]) & (box[2] > boxes[:, 0]) & (box[1] < boxes[:, 3])
                       & (box[3] > boxes[:, 1])))


def video_background_crops(video, npz, rng, per_video=120, size=CROP_SIZE, window=10, frame_stride=7):
    """(k, size, size, 3) uint8 RGB crops of one video that contain no labelled hand."""
    boxes, found = _hand_boxes(npz)
    cap = cv2.VideoCapture(str(video))
    frames = []
    i = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        if i % frame_stride == 0 and i < len(found) and found[i]:
            frames.append((i, frame))
        i += 1
    cap.release()
    if not frames:
        return np.zeros((0, size, size, 3), np.uint8)
    crops = []
    attempts = 0
    while len(crops) < per_video and attempts < per_video * 30:
        attempts += 1
        idx, frame = frames[rng.integers(len(frames))]
        h, w = frame.shape[:2]
        side = int(rng.uniform(0.15, 0.6) * min(h, w))
        x0, y0 = int(rng.integers(0, w - side + 1)), int(rng.integers(0, h - side + 1))
        near = [boxes[j] for j in range(max(0, idx - window), min(len(boxes), idx + window + 1))]
        near = np.concatenate(near) if near else np.zeros((0, 4))
        if _overlaps((x0, y0, x0 + side, y0 + side), near):
            continue
        crop = cv2.resize(frame[y0:y0 + side, x0:x0 + side], (size, size), interpolation=cv2.INTER_AREA)
        crops.append(crop[..., ::-1])
    return np.array(crops, np.uint8).reshape(-1, size, size, 3)


def build_real_cache(shared=None, path=None, per_video=120, seed=0, log=print):
    """Cut background crops from the shared videos into the cache; returns its path or None."""
    shared = shared or shared_data_dir()
    if shared is None:
        return None
    path = Path(path) if path else cache_dir() / f"backgrounds_v{CACHE_VERSION}.npy"
    rng = np.random.default_rng(seed)
    all_crops, sources = [], []
    for npz in sorted((shared / "video").rglob("*.mediapipe.npz")):
        if any(part in EXCLUDED_VIDEOS for part in npz.parts):
            continue
        video = npz.with_name(npz.name.replace(".mediapipe.npz", ".mp4"))
        if not video.exists():
            continue
        crops = video_background_crops(video, npz, rng, per_video=per_video)
        log(f"backgrounds: {len(crops)} crops from {video.relative_to(shared)}")
        all_crops.append(crops)
        sources.append({"video": str(video.relative_to(shared)), "crops": len(crops)})
    if not all_crops:
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    # a name of this process's own: handsynth's workers may each build the cache at once,
    # and whichever renames last leaves the same array in place
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npy")
    np.save(tmp, np.concatenate(all_crops))
    tmp.replace(path)
    path.with_suffix(".json").write_text(json.dumps({"version": CACHE_VERSION, "sources": sources}, indent=1))
    return path


def load_real_backgrounds(build=True, log=print):
    """(k,160,160,3) uint8 real crops (memory-mapped), building the cache if needed; None without shared/."""
    path = cache_dir() / f"backgrounds_v{CACHE_VERSION}.npy"
    if not path.exists():
        if not build or build_real_cache(path=path, log=log) is None:
            return None
    return np.load(path, mmap_mode="r")


# ---------------------------------------------------------------- procedural
def _fractal_noise(rng, size, octaves=5, persistence=0.55):
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = 2 ** (o + 1)
        grid = rng.random((cells + 1, cells + 1)).astype(np.float32)
        out += amp * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= persistence
    out /= total
    return (out - out.min()) / max(out.max() - out.min(), 1e-6)


def _palette(rng, k):
    cols = random_hsv_colours(rng, k, sat=(0.0, 0.55), val=(0.08, 0.95))
    return cols.astype(np.float32)


def _coords(size, angle):
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    return x * np.cos(angle) + y * np.sin(angle)


def procedural_background(rng, size):
    """(size,size,3) uint8 RGB texture of a random kind, possibly with shapes on top."""
    kind = rng.integers(5)
    if kind == 0:                                   # fractal noise through a colour ramp
        t = _fractal_noise(rng, size, octaves=int(rng.integers(3, 7)))[..., None]
        c = _palette(rng, 3)
        img = np.where(t < 0.5, c[0] + (c[1] - c[0]) * (2 * t), c[1] + (c[2] - c[1]) * (2 * t - 1))
    elif kind == 1:                                 # gradient + soft noise
        t = _coords(size, rng.uniform(0, 2 * np.pi))[..., None]
        t = (t - t.min()) / max(np.ptp(t), 1e-6)
        c = _palette(rng, 2)
        img = c[0] + (c[1] - c[0]) * t + 0.15 * (_fractal_noise(rng, size)[..., None] - 0.5)
    elif kind == 2:                                 # stripes or checks (fabric, tiles, blinds)
        freq = rng.uniform(3, 25)
        a = rng.uniform(0, np.pi)
        s = np.sin(2 * np.pi * freq * _coords(size, a))
        if rng.random() < 0.4:
            s = s * np.sin(2 * np.pi * freq * _coords(size, a + np.pi / 2))
        t = (s > rng.uniform(-0.5, 0.5)).astype(np.float32)[..., None] if rng.random() < 0.6 else (0.5 + 0.5 * s)[..., None]
        c = _palette(rng, 2)
        img = c[0] + (c[1] - c[0]) * t
    elif kind == 3:                                 # indoor-like: big shaded blocks with edges
        c = _palette(rng, 1)[0]
        img = np.broadcast_to(c, (size, size, 3)).copy()
        for _ in range(rng.integers(2, 6)):
            x0, y0 = rng.integers(-size // 2, size, 2)
            w, h = rng.integers(size // 4, size * 2, 2)
            col = _palette(rng, 1)[0]
            shade = (0.8 + 0.4 * _coords(size, rng.uniform(0, 2 * np.pi)))[..., None]
            mask = np.zeros((size, size), np.float32)
            cv2.rectangle(mask, (int(x0), int(y0)), (int(x0 + w), int(y0 + h)), 1.0, -1)
            img = img * (1 - mask[..., None]) + (col * shade) * mask[..., None]
    else:                                           # noise field with a vignette of light
        t = _fractal_noise(rng, size, octaves=3)[..., None]
        c = _palette(rng, 2)
        img = c[0] + (c[1] - c[0]) * t
        img = img * (0.7 + 0.6 * _fractal_noise(rng, size, octaves=2)[..., None])
    img = np.clip(img, 0, 1)
    if rng.random() < 0.6:
        img = _draw_shapes(rng, img, int(rng.integers(2, 14)))
    # like a room behind a hand at arm's length: light falls off across it, and it is
    # out of focus (the camera focuses on the hand)
    img = img * (0.65 + 0.5 * _fractal_noise(rng, size, octaves=2)[..., None])
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), rng.uniform(0.5, 4.0) * size / 128)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def _draw_shapes(rng, img, count):
    size = img.shape[0]
    img = np.ascontiguousarray(img, dtype=np.float32)
    for _ in range(count):
        if rng.random() < 0.2:      # skin-coloured distractor blobs
            col = SKIN_TONES[rng.integers(len(SKIN_TONES))] * rng.uniform(0.7, 1.1)
        else:
            col = random_hsv_colours(rng, 1)[0]
        col = tuple(float(x) for x in np.clip(col, 0, 1))
        shape = rng.integers(4)
        c = tuple(int(x) for x in rng.integers(0, size, 2))
        if shape == 0:
            r = int(rng.integers(3, size // 3))
            axes = (r, int(r * rng.uniform(0.3, 1.0)))
            cv2.ellipse(img, c, axes, float(rng.uniform(0, 180)), 0, 360, col, -1, cv2.LINE_AA)
        elif shape == 1:
            d = rng.integers(4, size // 2, 2)
            cv2.rectangle(img, c, (int(c[0] + d[0]), int(c[1] + d[1])), col, -1, cv2.LINE_AA)
        elif shape == 2:
            pts = rng.integers(-size // 4, size + size // 4, (int(rng.integers(3, 7)), 2)).astype(np.int32)
            cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
        else:
            p2 = tuple(int(x) for x in rng.integers(0, size, 2))
            cv2.line(img, c, p2, col, int(rng.integers(1, 6)), cv2.LINE_AA)
    return img


class BackgroundSource:
    """Random backgrounds at a given size: real crops (when available) and procedural ones.

    real: (k,S,S,3) uint8 or None; real_fraction: share of real ones when available.
    A pool of procedural textures is made up front and partly renewed on every call.
    """

    def __init__(self, rng, real=None, real_fraction=0.7, pool_size=192, pool_res=CROP_SIZE):
        self.real = real if real is not None and len(real) else None
        self.real_fraction = real_fraction if self.real is not None else 0.0
        self.pool_res = pool_res
        self.pool = np.stack([procedural_background(rng, pool_res) for _ in range(pool_size)])

    @property
    def kind(self):
        return "real+procedural" if self.real is not None else "procedural"

    def refresh(self, rng, count):
        """Replace `count` random pool textures with new ones."""
        for i in rng.integers(0, len(self.pool), count):
            self.pool[i] = procedural_background(rng, self.pool_res)

    def sample(self, rng, n, size):
        """(n,size,size,3) uint8 RGB: random sub-windows, flips and quarter turns."""
        out = np.empty((n, size, size, 3), np.uint8)
        use_real = rng.random(n) < self.real_fraction
        for i in range(n):
            src = self.real[rng.integers(len(self.real))] if use_real[i] else self.pool[rng.integers(len(self.pool))]
            s = src.shape[0]
            side = int(s * rng.uniform(0.45, 1.0))
            x0, y0 = rng.integers(0, s - side + 1, 2)
            win = np.asarray(src[y0:y0 + side, x0:x0 + side])
            if rng.random() < 0.5:
                win = win[:, ::-1]
            if not use_real[i] and rng.random() < 0.5:
                win = np.rot90(win, int(rng.integers(1, 4)))
            out[i] = cv2.resize(np.ascontiguousarray(win), (size, size),
                                interpolation=cv2.INTER_AREA if side > size else cv2.INTER_LINEAR)
        return out, use_real
