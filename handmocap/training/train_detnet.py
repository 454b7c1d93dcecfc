"""Train DetNet on CPU and export it (`handtrain detnet`; to RUN_DIR/detnet.onnx unless --export says where).

    handsynth generate -n 8192 -o runs/detnet_data/synth_train_0 --seed 1000   # (and _1, _2, ...)
    handsynth generate -n 1024 -o runs/detnet_data/synth_val --seed 424242
    handtrain detnet                          # fast backbone, from scratch (runs/detnet/fast/)
    handtrain detnet --resume --iters 30000   # continue runs/detnet/fast/last.pt
    handtrain detnet --export-only            # write the ONNX file from last.pt (--export models/detnet.onnx ships it)
    handtrain detnet --backbone fast-deep --init-from runs/detnet/fast3/last.pt   # grow a trained net
    handtrain detnet --backbone fast-deep --init-from models/detnet.onnx        # ... or the shipped one

Each batch (drawn from numpy generator [seed, iteration], so a resumed run sees the
batches the uninterrupted run would have) mixes:
* synthetic crops (handsynth shards, --data): all heads. Left hands are mirrored to the
  right and the 3D label's x negated (DESIGN.md);
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
Losses: heatmap 100 (per-cell MSE, sigma = 1 cell Gaussians), location 10, delta 1
(squared error weighted by H_gt + 0.1, normalised by the weight sum, so every joint's
map also learns its value away from the peak), presence and handedness BCE 1, AdamW
weight decay (L_reg).
Validation (never training data): held-out synthetic shards (--val), the held-out tail
of every training video (last 15% of frames, 15 frames gap), howiema 001 sequences L8/R8
(not used for training) and the held-back people's crops (`people_*`: error / hand size
and PCK at 0.1 of it, against MediaPipe's labels).
"""
import glob
import json
import os
import time
from pathlib import Path

import cv2
import numpy as np

from handmocap.training import real_data
from handmocap.perception.detector import hand_angle
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.skeleton import BONES, ROOT, normalize_joints
from handmocap.training.training import warmup_cosine_lr

RUN_DIR = Path("runs/detnet")
DATA_DIR = Path("runs/detnet_data")
CTX = 176                    # real hand context crops: px, covering CTX_SCALE x the keypoint box
CTX_SCALE = 2.4
REAL_CACHE = "real_v5.npz"          # v2: + arm-only negatives; v3: frame edges repeated as the detector repeats them;
                                    # v4: + MediaPipe world landmarks of the video hands (xyz, has_3d);
                                    # v5: + video/wild, 11K Hands, images/scenes; pseudo-labels filtered
                                    # (real_data.reliable_hands); the held-back people, validation only
HELD_BACK_SOURCE = "heldback/"      # source prefix of the held-back people's crops (never trained on)
WILD_SOURCE = "wild/"              # source prefix of the training people's video/wild crops (--wild-share)
PART_CACHE = "parts_v1.npz"         # close-ups of part of a hand (build_part_cache), negatives for --part-neg
ARM_CACHE = "arms_v1.npz"           # an arm without its hand (build_arm_cache), negatives for --arm-neg
NEAR_CACHE = "near_v1.npz"          # the scene just beside a hand (build_near_cache), negatives for --near-neg
ELBOW_REACHES = (1.6, 2.0, 2.4)     # arm_crop reaches (crop sides beyond the wrist) by the elbow
PALM_M = 0.093               # |wrist - middle MCP| that real held-out 3D errors are quoted at (temugeb's median)


def add_arguments(p):
    p.add_argument("--backbone", choices=("fast", "fast-deep", "fast-deeper", "paper"), default="fast")
    p.add_argument("--iters", type=int, default=20000, help="total iterations (a resumed run continues to this)")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=2e-3, help="AdamW, cosine decay to lr/50 after 300 warm-up iterations")
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--data", nargs="*", default=[str(DATA_DIR / "synth_train_*")],
                   help="synthetic shard directories (globs; re-scanned every 500 iterations for new ones)")
    p.add_argument("--val", default=str(DATA_DIR / "synth_val"), help="held-out synthetic shard directory")
    p.add_argument("--shared", type=Path, default=SHARED_DATA, help="real data pack (default %(default)s)")
    p.add_argument("--share-real", type=float, default=0.25, help="share of real hand crops per batch")
    p.add_argument("--share-neg", type=float, default=0.12, help="share of no-hand crops per batch")
    p.add_argument("--share-left", type=float, default=0.3, help="share of hand crops presented as left hands")
    p.add_argument("--left-2d", type=float, default=0.0, metavar="W",
                   help="2D weight of the crops shown as left hands (default 0: they train presence and "
                        "handedness only). With W > 0 the heatmaps also learn to place the joints of a hand "
                        "mirrored the wrong way, so a wrong handedness call costs the 3D but not the 2D")
    p.add_argument("--real-3d", type=float, default=0.0, metavar="W",
                   help="3D weight of real video crops against their MediaPipe world landmarks, x MediaPipe's "
                        "score (default 0: real crops train 2D only, as the paper's)")
    p.add_argument("--upright", type=float, default=None, metavar="DEG",
                   help="turn each hand crop upright (wrist below the middle finger's base, from its 2D labels) "
                        "and then by +-DEG, as the detector's quarter-turned crops show hands (default: no "
                        "turning, +-90 deg about the crop as rendered or filmed)"),
    p.add_argument("--real-scale", type=float, nargs=2, default=(0.9, 1.1), metavar=("LO", "HI"),
                   help="a real hand crop's side is its keypoint box x 1.3 x uniform(LO, HI) (default 0.9 1.1, "
                        "the paper's; the detector's tracked crops are the box x 1.5, x 0.92-1.27 in 90%% of "
                        "frames on the training people's clips)")
    p.add_argument("--real-shift", type=float, default=0.1, metavar="S",
                   help="a real hand crop's centre moves by up to S of its side on each axis (default %(default)s)")
    p.add_argument("--wild-share", type=float, default=None, metavar="P",
                   help="share of the real hand crops drawn from the video/wild clips of the training people "
                        "(default: as many as the real cache holds, about 0.28 in cache v5)")
    p.add_argument("--hand-weight", type=float, default=LOSS_WEIGHTS["hand"], metavar="W",
                   help="weight of the handedness loss (default %(default)s); higher asks the backbone itself "
                        "for features that tell a right hand from a left one")
    p.add_argument("--coord-weight", type=float, default=LOSS_WEIGHTS["coord"], metavar="W",
                   help="weight of the soft-argmax coordinate loss (default %(default)s); since session 17 the "
                        "exported read-out is that soft-argmax")
    p.add_argument("--fine-head", action="store_true",
                   help="add the fine (32x32) heatmaps (detnet.FineHeatmaps) and export their read-out if it "
                        "measures best on held-out synthetic crops")
    p.add_argument("--train-only", nargs="+", default=None, metavar="MODULE",
                   help="train only these modules (e.g. `fine`); the rest stays as loaded, BatchNorm "
                        "statistics included")
    p.add_argument("--grey", type=float, default=0.0, metavar="P",
                   help="share of crops shown in grey (a mono or IR camera; default %(default)s)")
    p.add_argument("--degrade", type=float, default=0.0, metavar="P",
                   help="share of hand crops degraded as real cameras and scenes degrade them: a patch of "
                        "another crop in front of the hand, the crop at a lower resolution, or sensor noise "
                        "(one of the three each; default %(default)s)")
    p.add_argument("--motion-blur", type=float, default=0.0, metavar="P",
                   help="share of hand crops smeared along a line of 3-15 px at a random angle (a hand moving "
                        "during the exposure), half of them also JPEG-compressed at quality 20-60 (a phone's "
                        "video; default %(default)s)")
    p.add_argument("--hand-occluder", type=float, default=0.0, metavar="P",
                   help="share of hand crops with another person's real hand put over part of them (two hands "
                        "touching, clasped or crossing), cut out along its joints (`hand_occluders`; default "
                        "%(default)s)")
    p.add_argument("--part-neg", type=float, default=0.0, metavar="P",
                   help="share of the no-hand crops that are close-ups of part of a real hand (a fingertip, "
                        "knuckles: the crop of a finder box on a hand that fills a photo), taught as no hand "
                        "(default %(default)s)")
    p.add_argument("--arm-neg", type=float, default=0.0, metavar="P",
                   help="share of the no-hand crops that show an arm without its hand: the frame's edge just "
                        "after a hand left it (`exit_crop`, the border repeated as the detector repeats it) or the "
                        "arm by the elbow, taught as no hand (default %(default)s)")
    p.add_argument("--near-neg", type=float, default=0.0, metavar="P",
                   help="share of the no-hand crops that show the scene just beside a hand (hair, a face, "
                        "clothes: where a track that lost its hand drifts), taught as no hand (default %(default)s)")
    p.add_argument("--max-synth", type=int, default=65536, help="synthetic crops kept in memory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (1 measured faster on the shared 2 cores)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda (a GPU, when one is lent)")
    p.add_argument("--amp", action="store_true",
                   help="bf16 mixed precision for the forward pass (autocast; the losses in float32): for --device cuda")
    p.add_argument("--workers", type=int, default=0, metavar="N",
                   help="processes that make the batches ahead (default 0: in the training loop, as on the 2-core "
                        "CPU); a GPU run wants about one per core")
    p.add_argument("--pack", type=Path, default=None, metavar="DIR",
                   help="train from a device pack (handmocap.training.device_pack: real and synthetic crops "
                        "as JPEGs, small enough to carry to a lent GPU) instead of --data, --val and --shared")
    p.add_argument("--write-pack", type=Path, default=None, metavar="DIR",
                   help="write a device pack of --data's synthetic crops, the held-out set and the real cache to "
                        "DIR (about --pack-mb MB) and stop")
    p.add_argument("--pack-mb", type=float, default=24.0, help="size of a --write-pack pack, MB (default %(default)s)")
    p.add_argument("--minutes", type=float, default=None,
                   help="stop after this many minutes of training and export (the learning rate decays over "
                        "whichever of --iters and --minutes comes first): a job that must end on time")
    p.add_argument("--val-every", type=int, default=250)
    p.add_argument("--ckpt-every", type=int, default=50)
    p.add_argument("--run-dir", type=Path, default=None, help="default runs/detnet/<backbone>")
    p.add_argument("--export", type=Path, default=None,
                   help="ONNX output (default RUN_DIR/detnet.onnx: the shipped models/detnet.onnx is replaced only "
                        "when you name it)")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/last.pt")
    p.add_argument("--export-only", action="store_true", help="export RUN_DIR/last.pt and stop")
    p.add_argument("--init-from", type=Path, default=None,
                   help="start from this checkpoint's weights (e.g. a `fast` run's last.pt for `fast-deep`: the "
                        "blocks it lacks start as the identity), or from an exported .onnx (models/detnet.onnx), "
                        "at iteration 0 with a fresh schedule and AdamW")


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


def build_real_cache(shared, path, seed=0, log=print):
    """Cut every usable real hand into a context crop (CTX px around its keypoint box x
    CTX_SCALE) and a few negatives per video frame; save the arrays to `path`.

    Hands: image (n,CTX,CTX,3), uv (n,21,2) in context px, right (n,) 1 if the hand appears
    as a right hand, weight (n,) label weight, held (n,) bool held-out, source (n,) str,
    xyz (n,21,3) MediaPipe's world landmarks made root-relative and scale-normalized (joint
    ROOT at 0, |j0 - j_ROOT| = 1; frame camera axes, the hand as it appears) and has_3d (n,)
    bool where there are any (the videos; howiema has 2D only).
    Negatives: neg (m,128,128,3) uint8, neg_held (m,) bool held-out, neg_arm (m,) bool an
    arm-only crop (`arm_crop`).
    """
    rng = np.random.default_rng([seed, 99])
    hands = {k: [] for k in ("image", "uv", "right", "weight", "held", "source", "xyz", "has_3d")}
    negs, neg_held, neg_arm = [], [], []

    def add_hand(image, uv, right, weight, held, source, world=None):
        cx, cy, side = real_data.crop_box(uv, CTX_SCALE)
        if side < 16:
            return
        M = real_data.crop_affine(cx, cy, side, CTX)
        hands["image"].append(real_data.warp(image, M, CTX, replicate=True))
        hands["uv"].append(real_data.apply_affine(M, uv).astype(np.float32))
        xyz = None if world is None else normalize_joints(world)
        has_3d = xyz is not None and bool(np.all(np.isfinite(xyz)))
        for k, v in (("right", right), ("weight", weight), ("held", held), ("source", source),
                     ("xyz", xyz.astype(np.float32) if has_3d else np.zeros((21, 3), np.float32)),
                     ("has_3d", has_3d)):
            hands[k].append(v)

    for seq in real_data.load_howiema(real_data.HOWIEMA_TRAIN_SUBJECT, shared):
        seq_name = seq["name"].split("/")[1]
        add_hand(seq["image"], seq["uv"], seq["handedness"] == "right", 1.0, seq_name in real_data.HOWIEMA_HELD_OUT,
                 "howiema001/" + seq_name)
    def add_video(video, split=real_data.video_split, stride=1, source=None, negatives=True):
        """The reliable pseudo-labelled hands (real_data.reliable_hands) of every `stride`-th
        frame where train | held ((F,) bool each, split(F)), and negatives beside them on
        every 3rd."""
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
                add_hand(image, lab["uv"][f, s], lab["handedness"][f, s] == 0, float(lab["score"][f, s]),
                         bool(held[f]), source or video.stem, lab["world"][f, s])
            if negatives and len(slots) and f % 3 == 0:    # negatives: squares of hand-like size, away from hands
                h, w = image.shape[:2]
                grown = [np.r_[b[:2] - 0.3 * (b[2:] - b[:2]) - 12, b[2:] + 0.3 * (b[2:] - b[:2]) + 12] for b in boxes]
                base = max(max(b[2] - b[0], b[3] - b[1]) for b in boxes) * 1.3
                for _ in range(4):
                    side = float(np.clip(base * rng.uniform(0.6, 1.6), 32, min(h, w)))
                    x0, y0 = rng.uniform(0, w - side), rng.uniform(0, h - side)
                    if not _boxes_overlap((x0, y0, x0 + side, y0 + side), grown):
                        M = real_data.crop_affine(x0 + side / 2, y0 + side / 2, side, 128)
                        negs.append(real_data.warp(image, M, 128, replicate=True))
                        neg_held.append(bool(held[f]))
                        neg_arm.append(False)
                        break
                for k, s in enumerate(slots):         # arm-only negatives: a tracked crop that slid up the forearm
                    arm = arm_crop(lab["uv"][f, s], rng)
                    if arm is None:
                        continue
                    box, others = arm_box(arm), [g for j, g in enumerate(grown) if j != k]
                    if not _boxes_overlap(box, others) and _inside_share(box, w, h) >= 0.8:   # mostly inside the frame: not a streak of repeated edge pixels
                        negs.append(real_data.warp(image, arm, 128, replicate=True))
                        neg_held.append(bool(held[f]))
                        neg_arm.append(True)
        log(f"  {video.name}: {len(hands['image'])} hands, {len(negs)} negatives so far")

    for rel in real_data.TRAIN_VIDEOS:
        add_video(Path(shared) / rel)
    # many more people (the pack's second drop): every 2nd frame of the training clips,
    # every 3rd of the held-back people's (validation only; their source says so)
    for held_back in (False, True):
        def whole(n):           # a clip is all training or all held out
            return np.full(n, not held_back), np.full(n, held_back)
        for video in real_data.wild_clips(shared, held_back):
            add_video(video, whole, stride=3 if held_back else 2,
                      source=f"{HELD_BACK_SOURCE}{video.stem}" if held_back else WILD_SOURCE + video.stem,
                      negatives=not held_back)
        for s in real_data.load_11khands(shared, held_back):
            add_hand(s["image"], s["uv"], s["handedness"] == "right", 1.0, held_back,
                     (HELD_BACK_SOURCE if held_back else "") + "11k/" + s["name"].split("/")[0])
        log(f"  11K Hands ({'held back' if held_back else 'training'} people): {len(hands['image'])} hands so far")
    for s in real_data.load_scenes(shared):
        add_hand(s["image"], s["uv"], s["handedness"] == "right", 1.0, False, "scenes")
    log(f"  images/scenes: {len(hands['image'])} hands")
    arrays = {k: np.asarray(v) for k, v in hands.items()}
    arrays["neg"], arrays["neg_held"] = np.asarray(negs, np.uint8).reshape(-1, 128, 128, 3), np.asarray(neg_held)
    arrays["neg_arm"] = np.asarray(neg_arm, bool)
    write_npz(path, arrays)
    return arrays


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
            return real_data.crop_affine(c[0], c[1], side, 128, angle_deg=rng.uniform(-30, 30))
    return None


def arm_box(M, size=128):
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
    return real_data.crop_affine(c[0], c[1], side, 128, angle_deg=rng.uniform(-180, 180))


def build_part_cache(shared, path, seed=0, log=print):
    """Close-ups of part of a hand (`part_crop`) cut from the training videos' full frames,
    one per labelled hand on every 3rd frame, and from howiema subject 001: part
    (m,128,128,3) uint8, part_held (m,) bool (the frames the real cache holds out)."""
    rng = np.random.default_rng([seed, 7])
    parts, held_out = [], []

    def add(image, uv, held):
        M = part_crop(uv, rng)
        if M is not None:
            parts.append(real_data.warp(image, M, 128, replicate=True))
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
    arrays = {kind: np.asarray(crops, np.uint8).reshape(-1, 128, 128, 3), f"{kind}_held": np.asarray(held_out, bool)}
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
    M = real_data.crop_affine(centre[0], centre[1], side, 128, angle_deg=rng.uniform(-180, 180))
    for other in others:
        if np.any(np.all(np.abs(real_data.apply_affine(M, other - shift) - 63.5) < 80, axis=1)):
            return None
    kept = image[:, lo:hi] if axis == 0 else image[lo:hi]
    return real_data.warp(np.ascontiguousarray(kept), M, 128, replicate=True)


def for_training_frames(shared, add_frame, progress, every_found_reliable=False):
    """add_frame(image (H,W,3) RGB, hands (k,21,2) reliable pseudo-labelled keypoints, held)
    for every 2nd frame of the training videos (held: their held-out tails), every 3rd of the
    training clips of video/wild and every images/scenes photo; progress(name) after each
    source. every_found_reliable: only frames whose every hand MediaPipe found is reliable.
    Never the held-back people."""
    videos = [(Path(shared) / rel, real_data.video_split, 2) for rel in real_data.TRAIN_VIDEOS]
    videos += [(v, lambda n: (np.ones(n, bool), np.zeros(n, bool)), 3) for v in real_data.wild_clips(shared)]
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
            for c in (crop, None if elbow is None else real_data.warp(image, elbow, 128, replicate=True)):
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
    return real_data.warp(image, real_data.crop_affine(cx, cy, side, 128, angle_deg=rng.uniform(-30, 30)), 128,
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
                  "near": (load_near, "crops beside a hand")}


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
    """The real cache (built on first use under runs/detnet_data/), or None without shared/."""
    if not (Path(shared) / "labelled2d").exists():
        log(f"note: no real data pack at {shared}; training on synthetic data only")
        return None
    return _cached(DATA_DIR / REAL_CACHE, lambda path: build_real_cache(shared, path, log=log),
                   f"cutting real crops from {shared}", log)


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
                 hard=None, real_scale=(0.9, 1.1), real_shift=0.1, wild_share=None):
        """hard: {kind: (its cache, share)} of HARD_NEGATIVES, each taught as that share of the
        negatives (a cache holds <kind> (m,128,128,3) and <kind>_held (m,) bool). real_scale
        (lo, hi): a real crop's side is the keypoint box x 1.3 x uniform(lo, hi); real_shift:
        its centre moves by up to this share of its side on each axis. wild_share: the share
        of the real crops drawn from the video/wild clips (None: as many as the cache holds)."""
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
        return np.degrees(hand_angle(uv)) + rng.uniform(-self.upright, self.upright, len(uv))

    def _present(self, n, appears_right, rng):
        """Which crops to show as left hands; mirror flag that makes the rest right hands."""
        show_left = rng.random(n) < self.share_left
        mirror = np.where(show_left, appears_right, ~appears_right)
        return show_left, mirror

    def _synth(self, n, rng):
        s = self.synth
        idx = rng.integers(0, len(s["image"]), n)
        show_left, mirror = self._present(n, s["handedness"][idx] == 0, rng)
        angle = self._angles(s["uv"][idx], rng)
        scale = rng.uniform(0.95, 1.05, n)
        shift = rng.uniform(-0.05, 0.05, (n, 2)) * 128
        images, uv = np.empty((n, 128, 128, 3), np.uint8), np.empty((n, 21, 2), np.float32)
        c = 63.5
        for i in range(n):
            M = real_data.crop_affine(c + shift[i, 0], c + shift[i, 1], 128 * scale[i], 128, angle[i], mirror[i])
            images[i] = real_data.warp(s["image"][idx[i]], M)
            uv[i] = real_data.apply_affine(M, s["uv"][idx[i]])
        xyz = rotate_mirror_3d(s["xyz_rel"][idx], angle, mirror).astype(np.float32)
        keypoints = (~show_left).astype(np.float32)
        w2d = np.where(show_left, self.left_2d, 1.0).astype(np.float32)
        return {"image": images, "uv": uv, "xyz": xyz, "w2d": w2d, "w3d": keypoints,
                "presence": np.ones(n, np.float32), "right": (~show_left).astype(np.float32),
                "w_hand": np.ones(n, np.float32)}

    def _real(self, n, rng):
        r = self.real
        if self.real_pools is None:
            idx = self.real_train[rng.integers(0, len(self.real_train), n)]
        else:
            wild, other = self.real_pools
            from_wild = rng.random(n) < self.wild_share
            idx = np.where(from_wild, wild[rng.integers(0, len(wild), n)], other[rng.integers(0, len(other), n)])
        show_left, mirror = self._present(n, r["right"][idx].astype(bool), rng)
        images, uv = np.empty((n, 128, 128, 3), np.uint8), np.empty((n, 21, 2), np.float32)
        side0 = (CTX - 1) / CTX_SCALE * 1.3           # the detector's crop side in context px
        angles = np.empty(n)
        for i in range(n):
            side = side0 * rng.uniform(*self.real_scale)
            cx, cy = (CTX - 1) / 2 + rng.uniform(-self.real_shift, self.real_shift, 2) * side
            angles[i] = self._angles(r["uv"][idx[i]][None], rng)[0]
            M = real_data.crop_affine(cx, cy, side, 128, angles[i], mirror[i])
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
                "presence": np.ones(n, np.float32), "right": (~show_left).astype(np.float32), "w_hand": weight}

    def _negatives(self, n, rng):
        counts = rng.multinomial(n, [share for _, _, share in self.hard] + [1 - sum(s for _, _, s in self.hard)])
        n_other = int(counts[-1])
        n_real = int(rng.binomial(n_other, 0.6)) if len(self.neg_train) else 0
        if self.procedural is None:
            n_real = n_other if len(self.neg_train) else 0
        images = [self.real["neg"][self.neg_train[rng.integers(0, len(self.neg_train), n_real)]]] if n_real else []
        if n_other - n_real:
            images.append(self.procedural.sample(rng, n_other - n_real, 128)[0])
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
            side = int(128 * rng.uniform(0.15, 0.45))
            x, y, sx, sy = rng.integers(0, 128 - side, 4)
            images[i, y:y + side, x:x + side] = images[rng.integers(len(images)), sy:sy + side, sx:sx + side]
        elif kind == 1:
            small = max(8, int(128 * rng.uniform(0.25, 0.6)))
            images[i] = cv2.resize(cv2.resize(images[i], (small, small), interpolation=cv2.INTER_AREA), (128, 128),
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


def hand_mask(uv, size=128, forearm=True):
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
        occ = cv2.warpAffine(real["image"][j], M, (128, 128), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
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


# ------------------------------------------------------------------ losses
def gaussian_heatmaps(uv, grid, stride, sigma=1.0):
    """(B,21,2) crop px -> (B,21,G,G) Gaussians of `sigma` cells, peak 1."""
    import torch
    from handmocap.training.detnet import uv_to_cell
    cell = uv_to_cell(uv, stride)
    g = torch.arange(grid, dtype=uv.dtype)
    dx2 = (g.view(1, 1, 1, grid) - cell[..., 0, None, None]) ** 2
    dy2 = (g.view(1, 1, grid, 1) - cell[..., 1, None, None]) ** 2
    return torch.exp(-0.5 * (dx2 + dy2) / sigma ** 2)


def detnet_losses(out, b, stride):
    """dict of scalar losses (unweighted) for a batch from to_torch."""
    import torch
    import torch.nn.functional as F

    from handmocap.training.detnet import bone_vectors
    heat = out["heatmap"]
    grid = heat.shape[-1]
    h_gt = gaussian_heatmaps(b["uv"], grid, stride)
    w2d = b["w2d"]
    l_heat = ((heat - h_gt) ** 2).mean((1, 2, 3))
    l_heat = (l_heat * w2d).sum() / w2d.sum().clamp_min(1e-6)
    w3d = b["w3d"]
    weight = (h_gt + 0.1).unsqueeze(2)                                      # (B,21,1,G,G)
    weight = weight / weight.sum((3, 4), keepdim=True)

    def map_loss(pred, target):                                             # pred (B,21,3,G,G), target (B,21,3)
        err = (((pred - target[..., None, None]) ** 2) * weight).sum((3, 4)).mean((1, 2))
        return (err * w3d).sum() / w3d.sum().clamp_min(1e-6)
    l_loc = map_loss(out["location"], b["xyz"])
    l_delta = map_loss(out["delta"], bone_vectors(b["xyz"]))
    l_coord = soft_argmax_loss(out["heat_logits"], b["uv"], b["presence"] * w2d, stride)
    fine = {}
    if "fine_logits" in out:        # the same two 2D losses on the fine grid (stride / 2; the same 8 px Gaussians)
        fine_heat = torch.sigmoid(out["fine_logits"])
        l_fine = ((fine_heat - gaussian_heatmaps(b["uv"], 2 * grid, stride / 2, sigma=2.0)) ** 2).mean((1, 2, 3))
        fine = {"fine_heat": (l_fine * w2d).sum() / w2d.sum().clamp_min(1e-6),
                "fine_coord": soft_argmax_loss(out["fine_logits"], b["uv"], b["presence"] * w2d, stride / 2)}
    l_presence = F.binary_cross_entropy_with_logits(out["presence"], b["presence"])
    wh = b["w_hand"] * torch.where(b["right"] > 0.5, 1.0, 1.0 / 0.6)        # ~balance the left share
    l_hand = (F.binary_cross_entropy_with_logits(out["handedness"], b["right"], reduction="none") * wh).sum() \
        / wh.sum().clamp_min(1e-6)
    return {"heat": l_heat, "coord": l_coord, "loc": l_loc, "delta": l_delta, "presence": l_presence,
            "hand": l_hand, **fine}


def soft_argmax_loss(heat_logits, uv, weight, stride):
    """Mean L1 distance in cells between the softmax-expected heatmap position and the label.

    heat_logits (B,21,G,G), uv (B,21,2) crop px, weight (B,) (0 for crops with no hand).
    The per-cell MSE on its own left the heatmaps near zero for the first thousand
    iterations (26 px error at 1,200 on 128 px crops): this term gives every joint a
    gradient towards its label from the first step. Joints outside the crop are skipped.
    """
    from handmocap.training.detnet import soft_argmax, uv_to_cell
    g = heat_logits.shape[-1]
    expected = soft_argmax(heat_logits)[0]                                        # (B,21,2) x, y
    target = uv_to_cell(uv, stride)
    inside = ((target >= -0.5) & (target <= g - 0.5)).all(-1).to(expected.dtype) * weight[:, None]
    err = (expected - target).abs().sum(-1)
    return (err * inside).sum() / inside.sum().clamp_min(1e-6)


# read-outs measured at each validation; the one best on held-out synthetic crops is exported
# (the first wins a tie, and is the one the real held-out sets are scored with)
READ_OUTS = ("softmax", "logquad", "soft3", "none")
LOSS_WEIGHTS = {"heat": 100.0, "coord": 0.5, "loc": 10.0, "delta": 1.0, "presence": 1.0, "hand": 1.0,
                "fine_heat": 100.0, "fine_coord": 0.25}     # fine cells are half as long: the same weight per px


def read_outs(net):
    """The read-outs `net` offers (READ_OUTS, and "fine" first with a fine head)."""
    return (("fine",) if getattr(net, "fine", None) is not None else ()) + READ_OUTS


# ------------------------------------------------------------------ validation
def shown_as_right(image, uv, xyz, left):
    """Copies of crops image (n,S,S,3), their joints uv (n,21,2) crop px and xyz (n,21,3)
    with the hands where left (n,) bool mirrored into right ones, as DetNet is shown them:
    the image flipped left-right, u -> S - 1 - u, x -> -x."""
    image, uv, xyz = image.copy(), uv.copy(), xyz.copy()
    image[left] = image[left][:, :, ::-1]
    uv[left, :, 0] = image.shape[2] - 1 - uv[left, :, 0]
    xyz[left, :, 0] *= -1
    return image, uv, xyz


def synth_val_set(path, limit=512):
    """Held-out synthetic crops as the detector sees them: left hands mirrored to the right
    (image, uv, xyz_rel), plus the unmirrored images for the handedness head. `path`: a
    shard directory, or the arrays load_synth gives (a device pack's)."""
    s = path if isinstance(path, dict) else load_synth([path], limit)
    if s is None:
        return None
    left = s["handedness"] == 1
    image, uv, xyz = shown_as_right(s["image"], s["uv"], s["xyz_rel"], left)
    bone_m = np.linalg.norm(s["xyz"][:, 0] - s["xyz"][:, ROOT], axis=-1)
    return {"image": image, "raw": s["image"], "uv": uv, "xyz": xyz, "in_image": s["in_image"],
            "right": (~left).astype(np.float32), "bone_m": bone_m}


def heldout_groups(source):
    """{group: (N,) bool} of real_val_set's crops by their `source` (N,): howiema 001, the
    training videos' held-out tails, the held-back people's clips and their photos."""
    source = np.asarray(source).astype(str)
    how, people = np.char.startswith(source, "howiema"), np.char.startswith(source, HELD_BACK_SOURCE)
    photos = np.char.startswith(source, HELD_BACK_SOURCE + "11k/")
    return {"howiema 001": how, "training videos' tails": ~how & ~people,
            "held-back clips": people & ~photos, "held-back photos": photos}


def real_val_set(real):
    """Held-out real crops at the detector's crop (box x 1.3, no jitter), shown as right
    hands: every howiema L8/R8 frame, every held-back person's hand in the cache and every
    3rd hand of the training videos' held-out tails."""
    if real is None:
        return None
    idx = np.flatnonzero(real["held"])
    how = np.char.startswith(real["source"][idx].astype(str), "howiema")
    people = np.char.startswith(real["source"][idx].astype(str), HELD_BACK_SOURCE)
    idx = np.concatenate([idx[how], idx[people], idx[~how & ~people][::3]])
    side = (CTX - 1) / CTX_SCALE * 1.3
    c = (CTX - 1) / 2
    images, uv = [], []
    for i in idx:
        M = real_data.crop_affine(c, c, side, 128, 0.0, not real["right"][i])
        images.append(real_data.warp(real["image"][i], M))
        uv.append(real_data.apply_affine(M, real["uv"][i]))
    out = {"image": np.asarray(images), "uv": np.asarray(uv, np.float32), "source": real["source"][idx],
           "neg": real["neg"][real["neg_held"]]}
    if "has_3d" in real:      # MediaPipe's world landmarks, mirrored as the crop is
        out["xyz"] = rotate_mirror_3d(real["xyz"][idx], np.zeros(len(idx)), ~real["right"][idx].astype(bool))
        out["has_3d"] = real["has_3d"][idx]
    return out


def predict(net, images, refines=("softmax",), batch=128):
    """Torch DetNet (eval) on uint8 crops (N,128,128,3), one pass -> {refine: (uv, xyz, conf)},
    presence (N,), right (N,) probabilities (numpy). `net` may also be an exported file
    (quantize_detnet.OnnxNet): its one read-out then stands for every refine asked."""
    if hasattr(net, "predict"):
        read, pres, right = net.predict(images, batch)
        return {r: read for r in refines}, pres, right
    import torch

    from handmocap.training.detnet import read_out
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    reads, pres, right = {r: [] for r in refines}, [], []
    with torch.no_grad():
        for i in range(0, len(images), batch):
            x = torch.from_numpy(np.ascontiguousarray(images[i:i + batch])).to(device).permute(0, 3, 1, 2).float() / 255.0
            out = {k: v.float() for k, v in net(x.contiguous(memory_format=torch.channels_last)).items()}
            for r in refines:
                reads[r].append([t.cpu().numpy() for t in read_out(out["heatmap"], out["location"], net.stride, r,
                                                                               out["heat_logits"], out.get("fine_logits"))])
            pres.append(torch.sigmoid(out["presence"]).cpu().numpy())
            right.append(torch.sigmoid(out["handedness"]).cpu().numpy())
    net.train(was_training)
    return ({r: [np.concatenate(k) for k in zip(*v)] for r, v in reads.items()},
            np.concatenate(pres), np.concatenate(right))


def pck_auc(err_mm, lo=20.0, hi=50.0, steps=15):
    """Paper's 3D PCK over thresholds linspace(20,50) mm -> AUC (trapezoid, normalised)."""
    th = np.linspace(lo, hi, steps)
    pck = (err_mm.reshape(-1)[:, None] <= th).mean(0)
    return float(np.trapezoid(pck, th) / (hi - lo))


def validate(net, sval, rval, refines=("softmax",)):
    """Held-out metrics; syn_px_<refine> for each read-out (2D px over in-crop joints)."""
    m = {}
    if sval is not None:
        reads, pres, _ = predict(net, sval["image"], refines)
        for refine, (uv, xyz, _) in reads.items():
            err2d = np.linalg.norm(uv - sval["uv"], axis=-1)[sval["in_image"]]
            m[f"syn_px_{refine}"] = float(err2d.mean())
            m[f"syn_pck5px_{refine}"] = float((err2d <= 5).mean())
        err3d = np.linalg.norm(xyz - sval["xyz"], axis=-1)
        m["syn_3d_norm"] = float(err3d.mean())
        err_mm = err3d * sval["bone_m"][:, None] * 1000
        m["syn_3d_mm"] = float(err_mm.mean())
        m["syn_3d_auc_20_50mm"] = pck_auc(err_mm)
        m["syn_presence"] = float((pres > 0.5).mean())
        right = predict(net, sval["raw"], ())[2]
        m["syn_handedness_acc"] = float(((right > 0.5) == (sval["right"] > 0.5)).mean())
    if rval is not None:
        reads, pres, _ = predict(net, rval["image"], refines[:1])
        err = np.linalg.norm(reads[refines[0]][0] - rval["uv"], axis=-1).mean(-1)
        source = rval["source"].astype(str)
        how = np.char.startswith(source, "howiema")
        people = np.char.startswith(source, HELD_BACK_SOURCE)
        if how.any():
            m["howiema001_heldout_px"] = float(err[how].mean())
        if (~how & ~people).any():
            m["video_heldout_px_vs_mediapipe"] = float(err[~how & ~people].mean())
        photos = np.char.startswith(source, HELD_BACK_SOURCE + "11k/")
        for name, mask in (("wild", people & ~photos), ("11k", people & photos)):
            if mask.any():      # people never trained on, against MediaPipe: error / hand size, PCK at 0.1 of it
                size = real_data.hand_size(rval["uv"][mask])
                joint_err = np.linalg.norm(reads[refines[0]][0][mask] - rval["uv"][mask], axis=-1)
                m[f"people_{name}_median_err"] = float(np.median(err[mask] / size))
                m[f"people_{name}_pck10"] = float((joint_err <= 0.1 * size[:, None]).mean())
        # the same crops mirrored the wrong way (a left hand shown as it is): what a wrong
        # handedness call costs the 2D
        flipped, uv_flipped, _ = shown_as_right(rval["image"], rval["uv"], np.zeros((len(err), 21, 3)),
                                                np.ones(len(err), bool))
        err_wrong = np.linalg.norm(predict(net, flipped, refines[:1])[0][refines[0]][0] - uv_flipped, axis=-1).mean(-1)
        if how.any():
            m["howiema001_heldout_px_wrong_side"] = float(err_wrong[how].mean())
        if (~how & ~people).any():
            m["video_heldout_px_wrong_side"] = float(err_wrong[~how & ~people].mean())
        if people.any():
            m["people_px"], m["people_px_wrong_side"] = float(err[people].mean()), float(err_wrong[people].mean())
        if "has_3d" in rval and rval["has_3d"].any():   # agreement with MediaPipe's 3D, not accuracy
            has = rval["has_3d"]
            err_mm = np.linalg.norm(reads[refines[0]][1][has] - rval["xyz"][has], axis=-1) * PALM_M * 1000
            m["video_heldout_3d_mm_vs_mediapipe"] = float(err_mm.mean())
            m["video_heldout_3d_auc_vs_mediapipe"] = pck_auc(err_mm)
        m["real_presence"] = float((pres > 0.5).mean())
        if len(rval["neg"]):
            m["neg_rejected"] = float((predict(net, rval["neg"], ())[1] < 0.5).mean())
        for kind in HARD_NEGATIVES:
            if len(rval.get(kind, ())):
                m[f"{kind}_rejected"] = float((predict(net, rval[kind], ())[1] < 0.5).mean())
    return m


def load_matching(net, state):
    """Load the tensors of `state` whose name and shape match `net`; -> the module names left fresh."""
    own = net.state_dict()
    keep = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    net.load_state_dict(keep, strict=False)
    return {k.rsplit(".", 2)[0] for k in own if k not in keep}


def unpadded(w, shape):
    """The exported conv weight `w` as DetNet's `shape`: itself, or with the zero channels that
    onnx_models.pad_depthwise_convs appended (output or input channels) cut off; None when
    it is neither."""
    if tuple(w.shape) == tuple(shape):
        return w
    if w.dim() != len(shape) or any(a < b for a, b in zip(w.shape, shape)) or w.shape[2:] != shape[2:]:
        return None
    rest = w.clone()
    rest[:shape[0], :shape[1]] = 0
    return w[:shape[0], :shape[1]] if not rest.any() else None


def state_from_onnx(path, images):
    """A trainable `DetNet` state dict recovered from an exported ONNX file (`path`), so the
    shipped model can seed training on a machine without its checkpoint.

    The export folds each BatchNorm into the convolution before it (W' = W*g/s, b' = b - m*g/s),
    so the file holds only the folded function. Each conv gets W' back and its BN is set up
    again around the statistics of W'x on `images` (N,128,128,3) uint8: with m and v the
    per-channel mean and variance there, BN(m, v, gamma=sqrt(v+eps), beta=b'+m) computes
    exactly W'x + b' in eval mode, and nearly so with batch statistics in training, so
    training goes on from the exported function. -> (state dict, backbone name).
    """
    import onnx
    import torch
    from onnx import numpy_helper

    from handmocap.training.detnet import DetNet
    model = onnx.load(str(path))
    doc = dict(p.split("=", 1) for p in model.doc_string.split() if "=" in p)
    backbone, fine = doc.get("backbone", "fast"), doc.get("fine", "0") == "1"
    params = {t.name: torch.from_numpy(numpy_helper.to_array(t).copy()) for t in model.graph.initializer}
    for node in model.graph.node:       # the exporter shares equal tensors (e.g. untrained biases) via Identity
        if node.op_type == "Identity" and node.input[0] in params:
            params[node.output[0]] = params[node.input[0]]
    net = DetNet(backbone, fine).eval()
    called = []                                         # convs in the order the forward pass calls them
    hooks = [m.register_forward_hook(lambda m, i, o: called.append(m))
             for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        net(torch.zeros(1, 3, 128, 128))
    for h in hooks:
        h.remove()
    convs = [n for n in model.graph.node if n.op_type == "Conv"]          # the graph keeps the call order
    if len(convs) != len(called):
        raise ValueError(f"{path}: {len(convs)} convolutions, a {backbone} DetNet has {len(called)}")
    bn_after = {seq[k]: seq[k + 1] for seq in net.modules() if isinstance(seq, torch.nn.Sequential)
                for k in range(len(seq) - 1) if isinstance(seq[k + 1], torch.nn.BatchNorm2d)}
    folded_bias = {}
    with torch.no_grad():
        for conv, node in zip(called, convs):
            w = unpadded(params[node.input[1]], conv.weight.shape)
            if w is None:
                raise ValueError(f"{path}: conv weight {tuple(params[node.input[1]].shape)} where DetNet has "
                                 f"{tuple(conv.weight.shape)}")
            conv.weight.copy_(w)
            b = params[node.input[2]][:w.shape[0]] if len(node.input) > 2 else torch.zeros(w.shape[0])
            if conv in bn_after:                        # an identity BN + b' until its statistics are known
                bn = bn_after[conv]
                folded_bias[bn] = b
                bn.weight.fill_(1.0), bn.bias.copy_(b), bn.running_mean.zero_(), bn.running_var.fill_(1.0 - bn.eps)
            else:
                conv.bias.copy_(b)
        for name, p in net.named_parameters():          # the linear heads keep their names
            if f"net.{name}" in params:
                p.copy_(params[f"net.{name}"])
        stats = {}                                      # BN -> its input W'x on `images` (the exported function's)
        hooks = [bn.register_forward_hook(lambda m, i, o: stats.__setitem__(m, i[0])) for bn in folded_bias]
        x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0
        net(x)
        for h in hooks:
            h.remove()
        for bn, b in folded_bias.items():
            mean, var = stats[bn].mean((0, 2, 3)), stats[bn].var((0, 2, 3), unbiased=False)
            bn.running_mean.copy_(mean), bn.running_var.copy_(var)
            bn.weight.copy_(torch.sqrt(var + bn.eps)), bn.bias.copy_(b + mean)
    return net.state_dict(), backbone


def identity_init_new_blocks(net, state):
    """Residual blocks of `net` that checkpoint `state` lacks get their last BN scale zeroed:
    each adds nothing at first, so the grown net computes what the loaded one did and
    training starts from there. -> their names."""
    from handmocap.training.detnet import InvertedResidual
    names = []
    for name, m in net.named_modules():
        if isinstance(m, InvertedResidual) and m.residual and f"{name}.body.2.1.weight" not in state:
            m.body[2][1].weight.data.zero_()
            names.append(name)
    return names


def main(args):
    if args.write_pack:                 # the data only: no network
        from handmocap.training.device_pack import HARD_KINDS, pack
        real, synth = load_real(args.shared), load_synth(synth_dirs(args.data), args.max_synth)
        val = load_synth([args.val], 256)
        if real is None or synth is None or val is None:
            raise SystemExit(f"--write-pack needs the real cache (the data pack at {args.shared}), synthetic shards "
                             f"({' '.join(args.data)}) and the held-out set ({args.val}): see the model card")
        # hard negatives only for a pack meant for a run that uses them: they take the room of rendered crops
        hard = {kind: HARD_NEGATIVES[kind][0](args.shared) for kind in HARD_KINDS if getattr(args, f"{kind}_neg")}
        pack(args.write_pack, real, synth, val, args.pack_mb, hard=hard)
        return
    import torch
    from tqdm import tqdm

    from handmocap.training.detnet import DetNet, export_onnx
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--device {args.device}: torch {torch.__version__} sees no CUDA device here; "
                         f"train on the CPU with --device cpu")
    run_dir = args.run_dir or RUN_DIR / args.backbone
    if args.export is None:   # never the shipped model by default: a trial run must not replace it
        args.export = run_dir / "detnet.onnx"
    net = DetNet(args.backbone, fine=args.fine_head).to(device, memory_format=torch.channels_last)
    trained = dict(net.named_parameters())
    if args.train_only:
        trained = {k: v for k, v in trained.items() if k.split(".")[0] in args.train_only}
        if not trained:
            raise SystemExit(f"--train-only {' '.join(args.train_only)}: no such module in a {args.backbone} "
                             f"DetNet (its modules: {', '.join(n for n, _ in net.named_children())})")
        for k, v in net.named_parameters():
            v.requires_grad_(k in trained)
    opt = torch.optim.AdamW(trained.values(), lr=args.lr, weight_decay=args.weight_decay)
    ckpt_path = run_dir / "last.pt"
    start, history, refine = 0, [], "softmax"
    if args.resume or args.export_only:
        if not ckpt_path.exists():
            raise SystemExit(f"no checkpoint at {ckpt_path}: train from scratch with `handtrain detnet`")
        ckpt = torch.load(ckpt_path, weights_only=False, map_location=device)
        fresh = load_matching(net, ckpt["model"])
        if fresh:                                   # an older checkpoint: new heads start fresh, so does AdamW
            print(f"note: {ckpt_path} lacks {', '.join(sorted(fresh))}; those start from scratch")
        else:
            opt.load_state_dict(ckpt["optimizer"])
        start, history, refine = ckpt["iteration"], ckpt["history"], ckpt.get("refine", refine)
        print(f"resumed {ckpt_path} at iteration {start}")
    if args.export_only:
        export_onnx(net, args.export, refine)
        print(f"exported {args.export} (refine {refine})")
        return

    if args.pack:                       # everything from the pack: nothing read from runs/detnet_data or shared
        from handmocap.training.device_pack import load_pack
        real, synth, synth_val = load_pack(args.pack)
        dirs, sval = [], synth_val_set(synth_val)
        print(f"pack {args.pack}: synthetic {len(synth['image'])} crops, held-out {len(synth_val['image'])}")
    else:
        dirs = synth_dirs(args.data)
        synth = load_synth(dirs, args.max_synth)
        if synth is None:
            raise SystemExit(f"no synthetic shards match {args.data}: run `handsynth generate -n 8192 -o "
                             f"{DATA_DIR}/synth_train_0` first")
        print(f"synthetic: {len(synth['image'])} crops from {len(dirs)} directories")
        real = load_real(args.shared)
        sval = synth_val_set(args.val) if (Path(args.val) / "meta.json").exists() else None
    if real is not None:
        print(f"real: {int((~real['held']).sum())} training hand crops, {int(real['held'].sum())} held out; "
              f"{int((~real['neg_held']).sum())} negatives ({int(real['neg_held'].sum())} held out)")
    hard = {}
    for kind, (load, what) in HARD_NEGATIVES.items():
        share = getattr(args, f"{kind}_neg")
        hard[kind] = load(args.shared) if real is not None and not args.pack else None
        if args.pack and kind in real:                  # the pack's own (training crops only)
            crops = real.pop(kind)
            hard[kind] = {kind: crops, f"{kind}_held": np.zeros(len(crops), bool)}
        if hard[kind] is not None:
            held = hard[kind][f"{kind}_held"]
            print(f"{what}: {int((~held).sum())} ({int(held.sum())} held out)"
                  + ("" if share else f", measured only (--{kind}-neg 0)"))
    maker = BatchMaker(synth, real, args.share_real, args.share_neg, args.share_left, args.upright, args.real_3d,
                       args.left_2d, {kind: (hard[kind], getattr(args, f"{kind}_neg")) for kind in HARD_NEGATIVES},
                       args.real_scale, args.real_shift, args.wild_share)
    if args.hand_occluder and not len(maker.real_train):
        raise SystemExit(f"--hand-occluder puts real hands over the crops: it needs the real training crops "
                         f"(the data pack at {args.shared}, or a --pack that holds them), and there are none")
    if sval is None:
        print(f"note: no held-out synthetic set at {args.val}")
    rval = real_val_set(real)
    for kind, pool in hard.items():
        if rval is not None and pool is not None:
            rval[kind] = pool[kind][pool[f"{kind}_held"]]
    if args.init_from and not args.resume:
        if args.init_from.suffix == ".onnx":        # an exported model: BN statistics from a batch of training crops
            try:
                state, source = state_from_onnx(args.init_from,
                                                maker.make(512, np.random.default_rng([args.seed, 2**31]))["image"])
            except Exception as e:                  # onnx's and protobuf's errors have no common base of their own
                raise SystemExit(f"--init-from {args.init_from}: not an exported DetNet "
                                 f"({type(e).__name__}: {str(e)[:200]})") from None
            print(f"recovered a trainable {source} DetNet from {args.init_from}")
        else:
            state = torch.load(args.init_from, weights_only=False, map_location=device)["model"]
        fresh = load_matching(net, state)
        grown = identity_init_new_blocks(net, state)
        print(f"initialised from {args.init_from}; new: {', '.join(sorted(fresh)) or 'nothing'} "
              f"(residual blocks starting as the identity: {', '.join(grown) or 'none'})")
    run_dir.mkdir(parents=True, exist_ok=True)

    def save(it):
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save({"model": net.state_dict(), "optimizer": opt.state_dict(), "iteration": it, "refine": refine,
                    "history": history, "backbone": args.backbone, "fine": args.fine_head,
                    "args": {k: str(v) for k, v in vars(args).items()}}, tmp)
        os.replace(tmp, ckpt_path)

    weights = {**LOSS_WEIGHTS, "hand": args.hand_weight, "coord": args.coord_weight}

    def train_mode():
        net.train()
        if args.train_only:             # frozen modules keep their BatchNorm statistics too
            for name, m in net.named_children():
                m.train(name in args.train_only)
    def batch_at(it):
        """Iteration it's batch (to_torch tensors on the CPU), the same wherever it is made."""
        rng = np.random.default_rng([args.seed, it])
        batch = maker.make(args.batch, rng)
        if args.degrade:
            degrade(batch["image"], batch["presence"] > 0, args.degrade, rng)
        if args.motion_blur:
            motion_blur(batch["image"], batch["presence"] > 0, args.motion_blur, rng)
        if args.hand_occluder:
            hand_occluders(batch["image"], batch["uv"], batch["presence"] > 0, args.hand_occluder, rng, maker.real,
                           maker.real_train)
        return to_torch(batch, rng, args.grey)

    def validate_and_save(done):
        """Validate, log, checkpoint and export at iteration `done` (`refine` becomes the
        read-out that measures best on held-out synthetic crops)."""
        nonlocal refine
        metrics = validate(net, sval, rval, refines=read_outs(net))
        if sval is not None:
            refine = min(read_outs(net), key=lambda r: metrics[f"syn_px_{r}"])
        history.append({"iteration": done, "seconds": time.monotonic() - t0, "refine": refine,
                        "synthetic_crops": len(synth["image"]), **metrics})
        bar.write(f"iter {done}: " + json.dumps({k: round(v, 4) if isinstance(v, float) else v
                                                 for k, v in history[-1].items()}))
        save(done)
        export_onnx(net, run_dir / "detnet.onnx", refine)

    # --workers N: N processes make the batches ahead (in order, each from its iteration's
    # seed, so a run gives the same batches either way), which keeps a GPU fed; they hold
    # the data as it was at the start (no new synthetic folders picked up)
    batches = iter(torch.utils.data.DataLoader(IterationBatches(batch_at, range(start, args.iters)), batch_size=None,
                                               num_workers=args.workers, prefetch_factor=4,
                                               pin_memory=device.type == "cuda")) if args.workers else None
    bar = tqdm(range(start, args.iters), initial=start, total=args.iters, desc=f"detnet-{args.backbone}",
               dynamic_ncols=True, mininterval=5)
    t0 = time.monotonic()
    budget_s = None if args.minutes is None else 60.0 * args.minutes
    done = start
    for it in bar:
        elapsed = time.monotonic() - t0
        if budget_s is not None and elapsed >= budget_s:
            bar.write(f"--minutes {args.minutes}: stopping at iteration {it}")
            break
        if it % 500 == 0 and it > start and len(synth["image"]) < args.max_synth and not args.workers and dirs:
            new_dirs = synth_dirs(args.data)
            if new_dirs != dirs:
                dirs, synth = new_dirs, load_synth(new_dirs, args.max_synth)
                maker.synth = synth
                bar.write(f"synthetic: now {len(synth['image'])} crops from {len(dirs)} directories")
        for group in opt.param_groups:
            # with --minutes, the cosine runs on whichever of iterations and time is further along
            # (the warm-up stays 300 iterations)
            at = it if budget_s is None or it < 300 else max(it, int(300 + (args.iters - 300) * elapsed / budget_s))
            group["lr"] = warmup_cosine_lr(at, args.lr, args.iters, warmup=300, floor=0.02)
        b = {k: v.to(device, non_blocking=True) for k, v in (next(batches) if batches else batch_at(it)).items()}
        train_mode()                    # validation and export leave every module in training mode
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.amp):   # --amp: bf16 mixed precision
            out = net(b["image"].contiguous(memory_format=torch.channels_last))
        losses = detnet_losses({k: v.float() for k, v in out.items()}, b, net.stride)
        loss = sum(weights[k] * v for k, v in losses.items())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if it % 20 == 0:
            bar.set_postfix({k: f"{v.item():.4f}" for k, v in losses.items()})
        done = it + 1
        if done % args.val_every == 0 or done == args.iters:
            validate_and_save(done)
        elif done % args.ckpt_every == 0:
            save(done)
    if done > start and (not history or history[-1]["iteration"] != done):      # stopped by --minutes
        validate_and_save(done)
    args.export.parent.mkdir(parents=True, exist_ok=True)
    export_onnx(net, args.export, refine)
    print(f"exported {args.export} ({args.export.stat().st_size / 1e6:.1f} MB, refine {refine}) "
          f"after {done} iterations")
