"""Choose the pose smoother's One Euro settings on the detector's real output.

    python research/tune_smoothing.py [--shared ../shared/data] [--sigma 1 1.5 2]

The filter defaults (handmocap.perception.pose.PoseSettings) were first set on synthetic jitter. Here
the detector and the shape estimate run once over the real clips of shared/data/video that
DetNet's and the finder's training used (real_data.TRAIN_VIDEOS; no evaluation split: this
chooses a filter, it measures no accuracy), every frame in order at the file's frame rate;
then the pose step runs with each candidate setting.

There is no ground truth for the motion, so the yardstick is the unsmoothed output itself,
smoothed without delay: a Gaussian of `sigma` frames run forwards and backwards over each
track's stretch of consecutive frames. A causal filter that smooths too little keeps the
frame-to-frame noise, one that smooths too much lags behind the motion: both show as
distance from that estimate. Per setting it prints that distance (mm; first and last 3
sigma frames of each stretch of >= 30 frames left out) and the jitter (the
second difference, mm per frame squared), each as RMS / median over frames and points. Rotations are scored on root-relative joints
(the hand's articulation and orientation, with the root filter as it is); the root filter
on the root (joint 9, the middle knuckle: HandPose.root) alone, where depth dominates.
"""
import argparse
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception import camera_info
from handmocap.training import real_data
from handmocap.perception.detector import HandDetector
from handmocap.perception.hand_model import HandModel
from handmocap.perception.ik_solver import IKSolver
from handmocap.perception.pose import PoseEstimator, PoseSettings
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.shape import ShapeEstimator

ROT = [(c, b) for c in (0.5, 1.0, 2.0, 4.0) for b in (0.5, 1.5, 5.0)]
ROOT = [(c, b) for c in (0.25, 0.5, 1.0, 2.0) for b in (0.5, 2.0, 8.0)]


def detect(shared: Path, model):
    """Per clip: (fps, K, [(hands, shapes) per frame]) of the detector and shape estimate."""
    out = {}
    for rel in real_data.TRAIN_VIDEOS:
        cap = cv2.VideoCapture(str(shared / rel))
        fps = cap.get(cv2.CAP_PROP_FPS) or 30.0
        detector, shapes, frames, K = HandDetector.load(), ShapeEstimator(model), [], None
        while True:
            ok, bgr = cap.read()
            if not ok:
                break
            K = camera_info.default_K(bgr.shape[1], bgr.shape[0]) if K is None else K
            hands = detector.process(bgr, len(frames) / fps)
            frames.append((hands, shapes.update(hands, len(frames) / fps)))
        cap.release()
        out[rel] = (fps, K, frames)
        print(f"  {rel}: {len(frames)} frames, a hand in {sum(bool(h) for h, _ in frames)}", flush=True)
    return out


def poses(clips, solver, model, params):
    """{(clip, track id): (frame indices (n,), root-relative joints (n,21,3) mm, root (n,3) mm)}."""
    seqs = {}
    for rel, (fps, K, frames) in clips.items():
        est = PoseEstimator(solver, model, **params)
        for i, (hands, shapes) in enumerate(frames):
            est.set_shapes(shapes)
            for h in est.update(hands, K, i / fps):
                s = seqs.setdefault((rel, h["track_id"]), ([], [], []))
                s[0].append(i)
                s[1].append(1e3 * (h["xyz"] - h["root"]))
                s[2].append(1e3 * h["root"])
    return {k: (np.array(a), np.array(b), np.array(c)) for k, (a, b, c) in seqs.items()}


def smooth_zero_phase(x, sigma):
    """(n,...) Gaussian-smoothed along axis 0, forwards and backwards (edges: nearest)."""
    r = int(np.ceil(3 * sigma))
    w = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    w /= w.sum()
    pad = np.concatenate([np.repeat(x[:1], r, 0), x, np.repeat(x[-1:], r, 0)])
    return sum(wk * pad[k:k + len(x)] for k, wk in enumerate(w))


def stretches(frames, min_len):
    """Index ranges of consecutive frame numbers at least min_len long."""
    cuts = np.flatnonzero(np.diff(frames) != 1) + 1
    return [(a, b) for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(frames)]) if b - a >= min_len]


MIN_STRETCH = 30   # frames: the same stretches for every sigma


def score(seqs, raw, part, sigma):
    """Distance from the zero-phase estimate of the raw output (RMS and median over frames of
    the per-point distance, mm) and jitter (RMS and median second difference, mm/frame²) of
    `part` (1: joints relative to the root, 2: root), over every stretch of every track."""
    edge = int(np.ceil(3 * sigma))
    dist, jit = [], []
    for key, (frames, *parts) in seqs.items():
        rframes, *rparts = raw[key]
        if not np.array_equal(frames, rframes):
            continue
        x, r = parts[part - 1], rparts[part - 1]
        for a, b in stretches(frames, MIN_STRETCH):
            ref = smooth_zero_phase(r[a:b], sigma)[edge:-edge]
            dist.append(np.linalg.norm(x[a:b][edge:-edge] - ref, axis=-1).reshape(len(ref), -1))
            jit.append(np.linalg.norm(np.diff(x[a:b], 2, axis=0), axis=-1).reshape(b - a - 2, -1))
    dist, jit = np.concatenate(dist), np.concatenate(jit)
    return (float(np.sqrt(np.mean(dist ** 2))), float(np.median(dist)),
            float(np.sqrt(np.mean(jit ** 2))), float(np.median(jit)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=SHARED_DATA)
    ap.add_argument("--sigma", type=float, nargs="+", default=[1.0, 1.5, 2.0],
                    help="widths (frames) of the zero-phase yardstick: all are printed, the best setting is "
                         "picked at the middle one")
    args = ap.parse_args()
    model = HandModel.load()
    solver = IKSolver.load(None, model=model)
    print("detecting:", flush=True)
    clips = detect(args.shared, model)
    raw = poses(clips, solver, model, {"smooth": False})
    rows = []
    for part, grid, keys in ((1, ROT, ("rot_min_cutoff", "rot_beta")), (2, ROOT, ("root_min_cutoff", "root_beta"))):
        for c, b in [(None, None)] + grid:
            params = {"smooth": False} if c is None else {keys[0]: c, keys[1]: b}
            seqs = raw if c is None else poses(clips, solver, model, params)
            d = [score(seqs, raw, part, s) for s in args.sigma]
            default = c == getattr(PoseSettings(), keys[0]) and b == getattr(PoseSettings(), keys[1])
            rows.append((part, c, b, default, d))
            name = "none (raw)" if c is None else f"{keys[0]} {c:g}, {keys[1]} {b:g}" + (" (default)" if default else "")
            print(f"{'joints rel. root' if part == 1 else 'root':16s} {name:42s} " +
                  "  ".join(f"sigma {s:g}: {rms:6.2f} / {med:5.2f} mm" for s, (rms, med, _, _) in zip(args.sigma, d)) +
                  f"  jitter {d[0][2]:6.2f} / {d[0][3]:5.2f}", flush=True)
    mid = len(args.sigma) // 2
    for part, label in ((1, "rotations"), (2, "root")):
        best = min((r for r in rows if r[0] == part and r[1] is not None), key=lambda r: r[4][mid][0])
        print(f"best {label} at sigma {args.sigma[mid]:g}: min_cutoff {best[1]:g}, beta {best[2]:g} "
              f"({best[4][mid][0]:.2f} mm; default "
              f"{next(r[4][mid][0] for r in rows if r[0] == part and r[3]):.2f} mm)")


if __name__ == "__main__":
    main()
