"""HandTracker.process on 640x480 frames with one tracked hand, the detector's parts, and
MediaPipe Hands (tracking/video mode) on the same frames when /tmp/mpenv has it.

    python benchmarks/bench_tracker.py [--video data/demo/hand_clip.mp4] [--repeat 3] [--threads 1]
                                       [--detnet PATH] [--finder PATH] [--iknet int8|float32|PATH]
                                       [--max-hands 2] [--set KEY=VALUE ...]

Prints median and p90 ms per frame of: the whole pipeline (HandTracker.process: detector +
shape + IKNet + FK + translation + smoothing), its stages as CPU ms per frame (one more pass
with each stage's function wrapped in a timer: detector with DetNet's onnxruntime call
inside it, shape, pose with IKSolver.solve, IKNet's onnxruntime call, clamp_to_limits and
pose_fields inside it; "rest" is the total minus the three stages), the detector alone (HandDetector.process),
DetNet alone on one crop and on a batch of 16 (crops/s), the hand finder on a frame, and
MediaPipe's ms per frame (scripts/mediapipe_reference.py --bench, a subprocess) with the
ratio. The first pass over the clip is a warm-up (the finder runs on the first frame
only; afterwards the hand is tracked). Wall time counts waiting for the CPU on a shared
machine; CPU time (time.process_time, one onnxruntime thread) is what a frame costs, which
is what an idle core would take.
"""
import argparse
import json
import os
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
MP_PYTHON = Path("/tmp/mpenv/bin/python")


def stage_cpu_ms(tracker, frames):
    """CPU ms per frame of HandTracker.process and of its stages, from one pass over frames
    with the stages' functions wrapped in timers (restored afterwards)."""
    import handmocap.pose as pose
    spent = {}

    def wrap(owner, name, key):
        fn, own = getattr(owner, name), name in vars(owner)     # own: a module function, not a method

        def timed_call(*args, **kwargs):
            c = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[key] = spent.get(key, 0.0) + time.process_time() - c
        setattr(owner, name, timed_call)
        return owner, name, fn, own

    solver, detnet = tracker.poses.solver, tracker.detector.detnet
    wrapped = [wrap(tracker.detector, "process", "detector"), wrap(tracker.shapes, "update", "shape"),
               wrap(tracker.poses, "update", "pose"), wrap(solver, "solve", "pose: IKSolver.solve"),
               wrap(pose, "clamp_to_limits", "pose: clamp_to_limits"), wrap(pose, "pose_fields", "pose: pose_fields")]
    sessions = detnet.session, solver.session      # onnxruntime sessions: run() timed through a proxy
    detnet.session = _TimedSession(sessions[0], "detector: DetNet network", spent)
    solver.session = _TimedSession(sessions[1], "pose: IKNet network", spent)
    total = 0.0
    try:
        for f in frames:
            c = time.process_time()
            tracker.process(f)
            total += time.process_time() - c
    finally:
        for owner, name, fn, own in wrapped:
            setattr(owner, name, fn) if own else delattr(owner, name)
        detnet.session, solver.session = sessions
    out = {"total": total, **spent}
    out["rest (tracker glue, smoothing)"] = total - sum(spent.get(k, 0.0) for k in ("detector", "shape", "pose"))
    return {k: round(1e3 * v / len(frames), 3) for k, v in out.items()}


class _TimedSession:
    """An onnxruntime session whose run() adds its CPU time to spent[key]."""

    def __init__(self, session, key, spent):
        self.session, self.key, self.spent = session, key, spent

    def __getattr__(self, name):
        return getattr(self.session, name)

    def run(self, *args, **kwargs):
        c = time.process_time()
        try:
            return self.session.run(*args, **kwargs)
        finally:
            self.spent[self.key] = self.spent.get(self.key, 0.0) + time.process_time() - c


def stats(times):
    """times: (wall s, process CPU s) pairs -> median/p90/min wall ms and median CPU ms
    (the minimum is the nearest to an idle machine's time)."""
    t = 1e3 * np.asarray(times)
    return {"median_ms": float(np.median(t[:, 0])), "p90_ms": float(np.percentile(t[:, 0], 90)),
            "min_ms": float(np.min(t[:, 0])),
            "median_cpu_ms": float(np.median(t[:, 1])), "n": len(t)}


def timed(fn, items, repeat):
    """Wall and CPU time of fn(x) for each x, `repeat` passes."""
    out = []
    for _ in range(repeat):
        for x in items:
            w, c = time.perf_counter(), time.process_time()
            fn(x)
            out.append((time.perf_counter() - w, time.process_time() - c))
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--video", default=str(ROOT / "data" / "demo" / "hand_clip.mp4"))
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads per network")
    p.add_argument("--detnet", help="DetNet: int8 (default, models/detnet_int8.onnx), float32 "
                                     "(models/detnet.onnx) or an ONNX path")
    p.add_argument("--finder", help="hand finder ONNX (default models/finder.onnx)")
    p.add_argument("--iknet", help="IKNet: int8 (default, models/iknet_int8.onnx), float32 or an ONNX path")
    p.add_argument("--max-hands", type=int, default=2, help="HandTracker/HandDetector max_hands (1: exactly one track)")
    p.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                   help="detector settings (HandDetector keywords), e.g. tracked_test_time_crops=4")
    args = p.parse_args()
    from handmocap.eval_cli import detector_settings
    settings = detector_settings(args.set)
    from handmocap.detector import HandDetector
    from handmocap.frames import read_video
    from handmocap.tracker import HandTracker

    frames = [cv2.resize(f, (640, 480)) if f.shape[:2] != (480, 640) else f for f in read_video(args.video)]
    from handmocap.ik_solver import model_path
    results = {"frames": len(frames), "load_avg": os.getloadavg()[0], "threads": args.threads,
               "max_hands": args.max_hands, "iknet": str(model_path(args.iknet)), "settings": settings}

    tracker = HandTracker(detnet=args.detnet, finder=args.finder, iknet=args.iknet, threads=args.threads,
                          max_hands=args.max_hands, **settings)
    for f in frames:                   # warm-up pass, and the hand is tracked from here on
        tracker.process(f)
    results["tracker"] = stats(timed(tracker.process, frames, args.repeat))
    results["tracker"]["hands_per_frame"] = float(np.mean([len(tracker.process(f)) for f in frames]))
    results["tracker_stages_cpu_ms_per_frame"] = stage_cpu_ms(tracker, frames)

    det = HandDetector.load(args.detnet, args.finder, threads=args.threads, max_hands=args.max_hands, **settings)
    for f in frames:
        det.process(f)
    results["detector"] = stats(timed(det.process, frames, args.repeat))
    results["detector"]["finder_runs_per_frame"] = det.stats["finder_runs"] / det.stats["frames"]

    crops = np.random.default_rng(0).integers(0, 255, (16, 128, 128, 3), np.uint8)
    one = stats(timed(lambda c: det.detnet(c[None]), list(crops), args.repeat * 4))
    batch = stats(timed(det.detnet, [crops] * 10, args.repeat))
    results["detnet_1_crop"] = {**one, "crops_per_s": 1e3 / one["median_ms"], "crops_per_cpu_s": 1e3 / one["median_cpu_ms"]}
    results["detnet_16_crops"] = {**batch, "crops_per_s": 16e3 / batch["median_ms"],
                                  "crops_per_cpu_s": 16e3 / batch["median_cpu_ms"]}
    results["finder"] = stats(timed(det.finder.find, frames[:30], args.repeat))

    if MP_PYTHON.is_file():
        r = subprocess.run([str(MP_PYTHON), str(ROOT / "scripts" / "mediapipe_reference.py"), "--bench", args.video],
                           capture_output=True, text=True)
        lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
        if r.returncode == 0 and lines:
            results["mediapipe_video_mode"] = json.loads(lines[-1])
            results["mediapipe_over_tracker"] = results["mediapipe_video_mode"]["median_ms"] / \
                results["tracker"]["median_ms"]
        else:
            results["mediapipe_video_mode"] = f"failed: {r.stderr[-300:]}"
    else:
        results["mediapipe_video_mode"] = "not measured: /tmp/mpenv absent"
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
