"""How much a One Euro filter on each track's published 2D joints moves the tracked figures.

Records the detector's hands on every frame of the wild clips once (default settings but
the filter off, shipped models), then replays the recording through per-track One Euro
filters of several settings and scores each as `handeval people` does
(eval_people.score_outputs: found, false hands, median error / hand size, PCK@0.1, shake):
settings are chosen on the training side, then read once on the held-back people.

    python research/keypoint_smoothing.py record --training-clips --out runs/s29/rec_train.pkl
    python research/keypoint_smoothing.py sweep runs/s29/rec_train.pkl
    python research/keypoint_smoothing.py demo      # the rendered demo clip's ground truth, filter on / off
"""
import argparse
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from handmocap.perception.one_euro import OneEuroFilter  # noqa: E402
from handmocap.training import eval_people, real_data  # noqa: E402


def record(args):
    from handmocap.perception.detector import HandDetector
    det = HandDetector.load(smooth_min_cutoff=None)       # the raw read-out: the filters are replayed here
    clips = []
    for video in real_data.wild_clips(real_data.SHARED_DATA, held_back=not args.training_clips):
        det.reset()
        frames = []
        for image, hands, reliable, sides in eval_people.frames_of_clip(video):
            out = [{k: h[k] for k in ("track_id", "uv", "handedness")} for h in det.process(image)]
            frames.append((out, hands, reliable, sides))
        clips.append({"name": video.stem, "fps": eval_people.clip_fps(video), "frames": frames})
        print(f"{video.stem}: {len(frames)} frames", flush=True)
    with open(args.out, "wb") as f:
        pickle.dump(clips, f)


def smoothed(clip, min_cutoff, beta):
    """The clip's frames with each track's uv through a One Euro filter on uv / the hand's
    size on the track's first frame (beta then has one meaning at any hand size; a size
    read anew each frame would shake the whole hand); a track unseen for a frame starts again."""
    filters, last_seen, unit = {}, {}, {}
    for f, (out, hands, reliable, sides) in enumerate(clip["frames"]):
        t = f / clip["fps"]
        new = []
        for h in out:
            tid, uv = h["track_id"], h["uv"]
            if tid not in filters or last_seen[tid] != f - 1:
                filters[tid] = OneEuroFilter(min_cutoff, beta, 1.0)
                unit[tid] = max(real_data.hand_size(uv), 1.0)
            last_seen[tid] = f
            new.append({**h, "uv": filters[tid](uv / unit[tid], t) * unit[tid] if min_cutoff else uv})
        yield new, hands, reliable, sides


def sweep(args):
    with open(args.recording, "rb") as f:
        clips = pickle.load(f)
    print("| min_cutoff Hz | beta | found % | false / frame | median | mean | PCK@0.1 | shake (MediaPipe's) |")
    print("|---|---|---|---|---|---|---|---|")
    for mc in args.min_cutoff:
        for beta in (args.beta if mc else [0.0]):
            m = eval_people.summary(eval_people.merge([eval_people.score_outputs(smoothed(c, mc, beta))
                                                       for c in clips]))
            print(f"| {mc} | {beta} | {100 * m['found']:.1f} | {m['false_per_frame']:.3f} | {m['median_err']:.4f} | "
                  f"{m['mean_err']:.4f} | {m['pck']:.4f} | {m['shake']:.4f} ({m['mediapipe_shake']:.4f}) |",
                  flush=True)


def demo(args):
    """HandTracker over the rendered demo clip (its K and frame rate) with the 2D filter at its
    default and off: mean 2D error px, root error mm and posed joints' error mm against the
    clip's ground truth, and the 2D shake."""
    import cv2
    from handmocap.perception.skeleton import ROOT
    from handmocap.perception.tracker import HandTracker
    root_dir = Path(__file__).resolve().parents[1]
    truth = np.load(root_dir / "data/demo/hand_clip.npz")
    for name, kw in (("2D filter on (default)", {}), ("2D filter off", {"smooth_min_cutoff": None})):
        tracker, cap = HandTracker(**kw), cv2.VideoCapture(str(root_dir / "data/demo/hand_clip.mp4"))
        e2, eroot, ejoint, uvs, i = [], [], [], [], 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            hands = tracker.process(frame, truth["K"], stamp_ns=int(i * 1e9 / float(truth["fps"])))
            if hands:
                h = hands[0]
                e2.append(np.linalg.norm(h["uv"] - truth["uv"][i], axis=-1).mean())
                eroot.append(1e3 * np.linalg.norm(h["root"] - truth["xyz"][i, ROOT]))
                ejoint.append(1e3 * np.linalg.norm(h["xyz"] - truth["xyz"][i], axis=-1).mean())
                uvs.append(h["uv"])
            i += 1
        uvs = np.array(uvs)
        jit = np.median(np.linalg.norm(uvs[2:] - 2 * uvs[1:-1] + uvs[:-2], axis=-1))
        print(f"{name}: {len(e2)} of {i} frames; 2D {np.mean(e2):.2f} px; root mean {np.mean(eroot):.1f} mm, "
              f"median {np.median(eroot):.1f}; posed joints {np.mean(ejoint):.1f} mm; 2D shake median {jit:.2f} px")


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("--training-clips", action="store_true")
    r.add_argument("--out", required=True)
    s = sub.add_parser("sweep")
    s.add_argument("recording")
    s.add_argument("--min-cutoff", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0, 4.0, 8.0])
    s.add_argument("--beta", type=float, nargs="+", default=[0.0, 0.5, 2.0, 8.0])
    sub.add_parser("demo")
    a = p.parse_args()
    {"record": record, "sweep": sweep, "demo": demo}[a.cmd](a)
