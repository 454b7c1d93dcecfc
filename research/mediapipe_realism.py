"""Realism check of synthetic hand images: does MediaPipe Hands find the hand, and where?

Run with a throwaway environment that has MediaPipe (never a project dependency):

    python3.11 -m venv /tmp/mpenv
    /tmp/mpenv/bin/pip install mediapipe==0.10.21 opencv-python-headless numpy
    handsynth generate -n 500 -o /tmp/synth_crops
    /tmp/mpenv/bin/python research/mediapipe_realism.py /tmp/synth_crops [--upscale 256] [-n 500] [--pad 0.5]
    # the same measure on real webcam hands framed the same way (the reference):
    /tmp/mpenv/bin/python research/mediapipe_realism.py --real shared/data/labelled2d/howiema_lstm_pm

Reads the .npz shards directly (numpy only, no handmocap import). For each image it runs
mediapipe.solutions.hands (static images, up to 2 hands, detection confidence 0.5) on the
image resized to --upscale px (MediaPipe's palm detector wants more pixels and context
than a 128 px crop; 0 keeps the size). Reports the share of images where a hand was
found; for found hands, the pixel error against the labels (mean over the 21 joints of
the detection closest to the labels, in the data set's pixels, and as a fraction of the
labelled hand box side); and how often MediaPipe's handedness matches the label.
--json writes the numbers and per-image results.
--conventions: also where MediaPipe puts the joints against the labels, on the hands it
read well (mean error under a quarter of the wrist-middle-MCP length |0-9|, every joint
in the image): the scale of its skeleton against the labels' (median least-squares
scale about the centroid), and then, with the labels scaled to its size, its offset along
the wrist -> middle MCP bone at the wrist, along the metacarpal (towards the wrist) at each
MCP, along the last bone (inwards) at each fingertip, and along the proximal bone at the
index and middle PIP, in units of |0-9|. On the engine's crops this is where MediaPipe's
landmark convention differs from the hand model's joints (docs/models_history.md, Evaluation).
"""
import argparse
import json
from pathlib import Path

import cv2
import numpy as np


def load(root, n):
    meta = json.loads((Path(root) / "meta.json").read_text())
    parts = {k: [] for k in ("image", "uv", "box", "handedness", "visible")}
    total = 0
    for name in meta["shards"]:
        with np.load(Path(root) / name) as data:
            for k in parts:
                parts[k].append(data[k])
            total += len(data["image"])
        if total >= n:
            break
    return {k: np.concatenate(v)[:n] for k, v in parts.items()}, meta


def real_webcam_crops(root, n, size=128, crop_scale=1.3, joint_to_vertex_box=1.16, seed=0):
    """Real hands framed like the engine's crops, as a reference for the same measure.

    root: shared/data/labelled2d/howiema_lstm_pm (256 px webcam frames, 21 labelled
    joints, MediaPipe order = ours). The square crop is the joints' box x
    `joint_to_vertex_box` (the median ratio of the engine's vertex box to its joint box)
    x crop_scale x U(0.85, 1.2), centre jittered by up to 8%, replicated border outside the
    frame, resized to `size`. Returns the dict `load` returns (box: the joints' box)."""
    rng = np.random.default_rng(seed)
    items = []
    for label_file in sorted(Path(root, "label").glob("*/*.json")):
        labels = json.loads(label_file.read_text())
        for key, pts in labels.items():
            if key != "offset":
                items.append((label_file.parent.name, label_file.stem, key, np.asarray(pts, np.float64)))
    order = rng.permutation(len(items))[:n]
    out = {k: [] for k in ("image", "uv", "box", "handedness", "visible")}
    for i in order:
        subject, seq, key, uv = items[i]
        frame = cv2.imread(str(Path(root, "frames", subject, seq, f"{seq[0]}{key}.jpg")))[..., ::-1]
        lo, hi = uv.min(0), uv.max(0)
        side = (hi - lo).max() * joint_to_vertex_box * crop_scale * rng.uniform(0.85, 1.2)
        centre = 0.5 * (lo + hi) + rng.uniform(-0.08, 0.08, 2) * (hi - lo).max() * joint_to_vertex_box
        s = size / side
        M = np.float32([[s, 0, size / 2 - s * centre[0]], [0, s, size / 2 - s * centre[1]]])
        out["image"].append(cv2.warpAffine(np.ascontiguousarray(frame), M, (size, size), flags=cv2.INTER_AREA,
                                           borderMode=cv2.BORDER_REPLICATE))
        crop_uv = uv * s + M[:, 2]
        out["uv"].append(crop_uv)
        out["box"].append(np.r_[crop_uv.min(0), crop_uv.max(0)])
        out["handedness"].append(int(seq[0] == "L"))
        out["visible"].append(np.ones(21, bool))
    data = {k: np.stack(v) for k, v in out.items()}
    return data, {"config": {"mode": "real webcam crop"}, "backgrounds": "real"}


def print_conventions(labels, found_uv):
    """Scale and per-joint offsets of MediaPipe's joints found_uv (N,21,2; NaN: not found)
    against the labels (N,21,2), as the module doc describes."""
    palm = np.linalg.norm(labels[:, 9] - labels[:, 0], axis=-1)
    err = np.linalg.norm(found_uv - labels, axis=-1).mean(1) / palm
    side = labels.max() + 1
    good = np.isfinite(err) & (err < 0.25) & ((labels >= 0) & (labels < side)).all(axis=(1, 2))
    U, M = labels[good], found_uv[good]
    Uc, Mc = U - U.mean(1, keepdims=True), M - M.mean(1, keepdims=True)
    scale = (Uc * Mc).sum((1, 2)) / (Uc * Uc).sum((1, 2))
    print(f"  conventions, on the {int(good.sum())} hands read within 0.25 |0-9|: MediaPipe's skeleton is "
          f"{np.median(scale):.3f} x the labels' (median; IQR {np.percentile(scale, 25):.3f}-"
          f"{np.percentile(scale, 75):.3f})")
    A = scale[:, None, None] * Uc + M.mean(1, keepdims=True)        # the labels at MediaPipe's size
    unit = palm[good] * scale

    def along(j, towards):                                          # offset of joint j towards joint `towards`
        d = A[:, towards] - A[:, j]
        return float(np.median(((M[:, j] - A[:, j]) * d / np.linalg.norm(d, axis=-1, keepdims=True)).sum(-1) / unit))
    rows = [("wrist, towards the middle MCP", along(0, 9))]
    rows += [(f"MCP {j}, towards the wrist", along(j, 0)) for j in (5, 9, 13, 17)]
    rows += [(f"tip {j}, inwards", along(j, j - 1)) for j in (4, 8, 12, 16, 20)]
    rows += [(f"PIP {j}, towards its MCP", along(j, j - 1)) for j in (6, 10)]
    for name, value in rows:
        print(f"    {name:32s} {value:+.3f} |0-9|")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", type=Path, help="a directory written by `handsynth generate`, or with --real the "
                    "howiema_lstm_pm folder of shared/data/labelled2d")
    ap.add_argument("--real", action="store_true", help="real webcam frames cropped like the engine's crops")
    ap.add_argument("-n", type=int, default=500)
    ap.add_argument("--upscale", type=int, default=256, help="side in px fed to MediaPipe (0: as stored)")
    ap.add_argument("--pad", type=float, default=0.0,
                    help="add this fraction of the side as replicated border on each side (more context)")
    ap.add_argument("--min-confidence", type=float, default=0.5)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--conventions", action="store_true", help="also the scale and per-joint offsets of "
                    "MediaPipe's joints against the labels (see the module doc)")
    args = ap.parse_args()

    import mediapipe as mp
    data, meta = real_webcam_crops(args.data, args.n) if args.real else load(args.data, args.n)
    n, size = len(data["image"]), data["image"].shape[1]
    side = args.upscale or size
    found = np.zeros(n, bool)
    err_px = np.full(n, np.nan)
    hand_match = np.zeros(n, bool)
    mp_uv = np.full((n, 21, 2), np.nan)
    with mp.solutions.hands.Hands(static_image_mode=True, max_num_hands=2,
                                  min_detection_confidence=args.min_confidence) as hands:
        pad = 0
        for i in range(n):
            img = data["image"][i]
            pad = int(round(args.pad * size))
            if pad:
                img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
            if side != img.shape[0]:
                img = cv2.resize(img, (side, side), interpolation=cv2.INTER_CUBIC)
            result = hands.process(np.ascontiguousarray(img))
            if not result.multi_hand_landmarks:
                continue
            found[i] = True
            best = None
            for lm, hd in zip(result.multi_hand_landmarks, result.multi_handedness):
                uv = np.array([(p.x, p.y) for p in lm.landmark]) * (size + 2 * pad) - pad   # data-set pixels
                e = np.linalg.norm(uv - data["uv"][i], axis=1).mean()
                if best is None or e < best[0]:
                    best = (e, hd.classification[0].label, uv)
            err_px[i] = best[0]
            mp_uv[i] = best[2]
            # solutions.hands labels assume a mirrored (selfie) image: on these unmirrored images its
            # "Right" is a left hand (as scripts/mediapipe_reference.py swaps it)
            hand_match[i] = (best[1] == "Right") == bool(data["handedness"][i])
    box = data["box"]
    box_side = np.maximum(box[:, 2] - box[:, 0], box[:, 3] - box[:, 1])
    rel = err_px / box_side
    ok = found
    summary = {
        "data": str(args.data), "images": n, "image_px": size, "fed_px": side,
        "mode": meta["config"]["mode"], "backgrounds": meta.get("backgrounds"),
        "found_rate": float(found.mean()),
        "mean_error_px": float(np.nanmean(err_px)) if ok.any() else None,
        "median_error_px": float(np.nanmedian(err_px)) if ok.any() else None,
        "median_error_box_fraction": float(np.nanmedian(rel)) if ok.any() else None,
        "within_10pct_box_rate": float(np.mean(rel[ok] < 0.1)) if ok.any() else None,
        "handedness_agreement": float(hand_match[ok].mean()) if ok.any() else None,
    }
    print(f"MediaPipe Hands on {n} synthetic {summary['mode']} images ({size} px, fed at {side} px): "
          f"found {100 * summary['found_rate']:.1f}%")
    if ok.any():
        print(f"  joint error of found hands: mean {summary['mean_error_px']:.2f} px, median "
              f"{summary['median_error_px']:.2f} px ({100 * summary['median_error_box_fraction']:.1f}% of the hand "
              f"box); {100 * summary['within_10pct_box_rate']:.1f}% of hands within 10% of the box; "
              f"handedness agrees {100 * summary['handedness_agreement']:.1f}%")
    if args.conventions:
        print_conventions(data["uv"], mp_uv)
    if args.json:
        args.json.write_text(json.dumps({**summary, "found": found.tolist(),
                                         "error_px": [None if np.isnan(e) else float(e) for e in err_px]}, indent=1))


if __name__ == "__main__":
    main()
