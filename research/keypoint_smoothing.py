"""How much a One Euro filter on each track's published 2D joints moves the tracked figures.

Records the detector's hands on every frame of the wild clips once (default settings,
shipped models), then replays the recording through per-track One Euro filters of several
settings and scores each as `handeval people` does (found, false hands, median error / hand
size, PCK@0.1) -- settings are chosen on the training side, then read once on the held-back
people.

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
    det = HandDetector.load()
    clips = []
    for video in real_data.wild_clips(real_data.SHARED_DATA, held_back=not args.training_clips):
        fps = float(real_data.load_pseudo_labels(video)["fps"])
        fps = 30.0 if not 1 <= fps <= 240 else fps          # SHREYASH1504__recorded_video says 1000
        det.reset()
        frames = []
        for image, hands, reliable, sides in eval_people.frames_of_clip(video):
            out = [(h["track_id"], h["uv"].copy(), h["handedness"]) for h in det.process(image)]
            frames.append((out, hands, reliable, sides))
        clips.append({"name": video.stem, "fps": fps, "frames": frames})
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
        for tid, uv, side in out:
            if tid not in filters or last_seen[tid] != f - 1:
                filters[tid] = OneEuroFilter(min_cutoff, beta, 1.0)
                unit[tid] = max(real_data.hand_size(uv), 1.0)
            last_seen[tid] = f
            size = unit[tid]
            new.append((tid, filters[tid](uv / size, t) * size if min_cutoff else uv, side))
        yield new, hands, reliable, sides


def score(frames):
    out = {"frames": 0, "labelled": 0, "found": 0, "false": 0, "err": [], "joint_err": [], "right_side": []}
    for hands_out, hands, reliable, sides in frames:
        out["frames"] += 1
        out["labelled"] += len(hands)
        hit = set()
        for _, uv, side in hands_out:
            k, dist = eval_people.nearest_label(uv, hands)
            if dist >= eval_people.ON_HAND:
                out["false"] += 1
                continue
            hit.add(k)
            if reliable[k]:
                joint = np.linalg.norm(uv - hands[k], axis=-1) / real_data.hand_size(hands[k])
                out["err"].append(joint.mean())
                out["joint_err"].append(joint)
                out["right_side"].append(side == sides[k])
        out["found"] += len(hit)
    for k in ("err", "right_side"):
        out[k] = np.asarray(out[k])
    out["joint_err"] = np.asarray(out["joint_err"]).reshape(-1, 21)
    return out


def jerk(clip, min_cutoff, beta):
    """Median over tracked joints of |uv(t+1) - 2 uv(t) + uv(t-1)| / hand size: the frame-to-frame
    shake a robot would follow."""
    hist, acc = {}, []
    for out, *_ in smoothed(clip, min_cutoff, beta):
        for tid, uv, _ in out:
            h = hist.setdefault(tid, [])
            h.append(uv)
            if len(h) >= 3:
                acc.append(np.median(np.linalg.norm(h[-1] - 2 * h[-2] + h[-3], axis=-1)) / real_data.hand_size(uv))
        for tid in [t for t in hist if t not in {o[0] for o in out}]:
            del hist[tid]
    return acc


def label_jerk(clip):
    acc = []
    prev = []
    for _, hands, reliable, _ in clip["frames"]:
        prev.append(hands if len(hands) == 1 else None)
        if len(prev) >= 3 and all(p is not None for p in prev[-3:]):
            a, b, c = prev[-3][0], prev[-2][0], prev[-1][0]
            acc.append(np.median(np.linalg.norm(c - 2 * b + a, axis=-1)) / real_data.hand_size(c))
    return acc


def sweep(args):
    with open(args.recording, "rb") as f:
        clips = pickle.load(f)
    print(f"MediaPipe's labels, one-hand frames: jerk median {np.median(sum((label_jerk(c) for c in clips), [])):.4f}")
    print("| min_cutoff Hz | beta | found % | false / frame | median | mean | PCK@0.1 | jerk median |")
    print("|---|---|---|---|---|---|---|---|")
    for mc in args.min_cutoff:
        for beta in (args.beta if mc else [0.0]):
            m = eval_people.summary(eval_people.merge([score(smoothed(c, mc, beta)) for c in clips]))
            j = np.median(sum((jerk(c, mc, beta) for c in clips), []))
            print(f"| {mc} | {beta} | {100 * m['found']:.1f} | {m['false_per_frame']:.3f} | {m['median_err']:.4f} | "
                  f"{m['mean_err']:.4f} | {m['pck']:.4f} | {j:.4f} |", flush=True)


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
