"""HandTracker.process against MediaPipe Hands, matched, and the tracker's parts.

    python benchmarks/bench_tracker.py [--videos V ...] [--max-hands 1 2] [--rounds 5] [--repeat 1] [--threads 1] [--in-turn]
                                       [--detnet PATH] [--finder PATH] [--iknet int8|float32|PATH]
                                       [--set KEY=VALUE ...]

Matched comparison (first table): for each video (default: the demo clip and, where the
data pack is beside the repository, two real clips: one hand at 540x960, two hands at
1280x720) and each maximum number of hands (default 1 and 2), the median ms per frame of
HandTracker.process and of MediaPipe Hands in tracking mode (scripts/mediapipe_reference.py
--bench in /tmp/mpenv, a subprocess; built there when absent: eval_cli.reference_python) on the same frames at their own size, with the same
maximum number of hands, and the BGR -> RGB conversion MediaPipe needs counted on its side
(HandTracker takes the camera's BGR frames as they are); ratio = ours / MediaPipe's, the
median over `--rounds` alternating rounds (one pass each, after a warm-up pass).

Then, on the first video with the first max-hands: median and p90 ms per frame of the
whole pipeline (detector + shape + IKNet + FK + translation + smoothing), its stages as
CPU ms per frame (one more pass with each stage's function wrapped in a timer: detector
with DetNet's onnxruntime call inside it, shape, pose with IKSolver.solve, IKNet's
onnxruntime call, clamp_to_limits and pose_fields inside it; "rest" is the total minus the
three stages), the detector alone (HandDetector.process), DetNet alone on one crop and on a
batch of 16 (crops/s) and the hand finder on a frame. The first pass over a clip is a
warm-up. Wall time counts waiting for the CPU on a shared machine; CPU time
(time.process_time, every thread of the process, one onnxruntime thread per network) is what
a frame costs. Since session 39 the detector reads on a second thread too where the machine
has two cores (the finder beside the crops, the side network beside the keypoints, half the
crops beside the other half): wall time is then below CPU time where the second core is free.
MediaPipe's legacy solution works on one core (its CPU time per frame equals its wall time
here); `--in-turn` runs ours on one thread as well.
"""
import argparse
import json
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
from handmocap.training.eval_cli import add_model_arguments, detector_settings, reference_python  # noqa: E402
REAL_CLIPS = ("video/webcam/lujunwang_hand.mp4", "video/wild/Criminal-9527__hands.mp4")   # one hand, two hands
MAX_FRAMES = 200


def default_videos():
    """The demo clip, and the REAL_CLIPS of the data pack where it is beside the repository."""
    from handmocap.training.pose_data import SHARED_DATA
    return [ROOT / "data" / "demo" / "hand_clip.mp4"] + [SHARED_DATA / c for c in REAL_CLIPS
                                                          if (SHARED_DATA / c).is_file()]


def mediapipe_ms(video, max_hands, repeat=1):
    """MediaPipe's tracking mode on the video's first MAX_FRAMES frames (a subprocess in
    the MediaPipe venv): its JSON line (median_ms, hands_per_frame, ...) or a string saying why not."""
    python = reference_python()        # found, or built in /tmp/mpenv (said), or None (said why)
    if python is None:
        return "not measured: no MediaPipe venv (see the line above)"
    r = subprocess.run([str(python), str(ROOT / "scripts" / "mediapipe_reference.py"), "--bench", str(video),
                        "--frames", str(MAX_FRAMES), "--max-hands", str(max_hands),
                        "--repeat", str(repeat)], capture_output=True, text=True)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    return json.loads(lines[-1]) if r.returncode == 0 and lines else f"failed: {r.stderr[-300:]}"


def matched(videos, max_hands_list, args, settings):
    """Rows (dicts) of the matched comparison, and its markdown table. Each row is `rounds`
    rounds of one pass of ours then one of MediaPipe's (after a warm-up pass each), and
    the ratio is the median of the rounds' ratios: on a shared machine the speed of the
    whole machine drifts by a third over minutes (session 24), which a ratio of two runs
    minutes apart would take for a difference between the two."""
    from handmocap.runtime.frames import read_video
    from handmocap.perception.tracker import HandTracker
    rows = []
    for video in videos:
        frames = [f for _, f in zip(range(MAX_FRAMES), read_video(str(video)))]
        for max_hands in max_hands_list:
            tracker = HandTracker(detnet=args.detnet, side_detnet=args.side_detnet, finder=args.finder, iknet=args.iknet,
                                  threads=args.threads, max_hands=max_hands, **settings)
            if args.in_turn:
                one_thread(tracker.detector)
            hands = [len(tracker.process(f)) for f in frames]         # warm-up; the hands are tracked from here on
            ours, theirs, failed = [], [], None
            for _ in range(args.rounds):
                ours.append(stats(timed(tracker.process, frames, args.repeat)))
                mp = mediapipe_ms(video, max_hands, args.repeat)
                if not isinstance(mp, dict):
                    failed = mp
                    break
                theirs.append(mp)
            row = {"video": Path(video).name, "size": f"{frames[0].shape[1]}x{frames[0].shape[0]}",
                   "max_hands": max_hands, "rounds": len(ours),
                   "ours_ms": float(np.median([o["median_ms"] for o in ours])),
                   "ours_cpu_ms": float(np.median([o["median_cpu_ms"] for o in ours])),
                   "ours_hands_per_frame": float(np.mean(hands)), "mediapipe": failed}
            if theirs:
                ratios = [o["median_ms"] / m["median_ms"] for o, m in zip(ours, theirs)]
                if all("median_cpu_ms" in m for m in theirs):    # CPU against CPU: what a frame costs each
                    row["cpu_ratio"] = float(np.median([o["median_cpu_ms"] / m["median_cpu_ms"]
                                                        for o, m in zip(ours, theirs)]))
                row["mediapipe"] = {"median_ms": float(np.median([m["median_ms"] for m in theirs])),
                                    "hands_per_frame": theirs[-1]["hands_per_frame"]}
                row.update(ratio=float(np.median(ratios)), ratio_range=[float(min(ratios)), float(max(ratios))])
            rows.append(row)
            print(json.dumps(row), flush=True)
    table = ["| video | size | max hands | ours ms (hands/frame) | ours CPU ms | MediaPipe ms (hands/frame) | "
             "ours / MediaPipe, median (range) of the rounds | CPU ours / MediaPipe |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        mp = r["mediapipe"]
        mp_cell = f"{mp['median_ms']:.1f} ({mp['hands_per_frame']:.2f})" if isinstance(mp, dict) else mp
        table.append(f"| {r['video']} | {r['size']} | {r['max_hands']} | {r['ours_ms']:.1f} "
                     f"({r['ours_hands_per_frame']:.2f}) | {r['ours_cpu_ms']:.1f} | {mp_cell} | "
                     + (f"{r['ratio']:.2f} ({r['ratio_range'][0]:.2f}-{r['ratio_range'][1]:.2f}) |"
                        if "ratio" in r else "– |")
                     + (f" {r['cpu_ratio']:.2f} |" if "cpu_ratio" in r else " – |"))
    return rows, "\n".join(table)


def one_thread(detector):
    """Everything of a HandDetector on the caller's thread, as before session 39: the finder, the
    side network and each crop read one after the other (`--in-turn`)."""
    detector.finder_beside = False
    detector.detnet.beside = False


def stage_cpu_ms(tracker, frames):
    """CPU ms per frame of HandTracker.process and of its stages, from one pass over frames
    with the stages' functions wrapped in timers (restored afterwards); "networks" is the CPU of
    every onnxruntime run (DetNet, its side network, the finder, IKNet), on whichever thread it
    ran, and "glue" the rest: the Python and numpy around them (crops cut, tracks kept, poses
    built), issue 51's share."""
    import handmocap.perception.pose as pose
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

    solver, detector = tracker.poses.solver, tracker.detector
    wrapped = [wrap(detector, "process", "detector"), wrap(tracker.shapes, "update", "shape"),
               wrap(tracker.poses, "update", "pose"), wrap(solver, "solve", "pose: IKSolver.solve"),
               wrap(pose, "clamp_to_limits", "pose: clamp_to_limits"), wrap(pose, "hands_pose_fields", "pose: hands_pose_fields")]
    # onnxruntime sessions: run() timed through a proxy, each on its own thread's clock
    owners = [(detector.detnet, "detector: DetNet network"), (solver, "pose: IKNet network")]
    if getattr(detector.detnet, "side", None) is not None:
        owners.append((detector.detnet.side, "detector: side network"))
    if hasattr(detector.finder, "session"):
        owners.append((detector.finder, "detector: finder network"))
    sessions = [(owner, owner.session) for owner, _ in owners]
    for owner, key in owners:
        owner.session = _TimedSession(owner.session, key, spent)
    total = 0.0
    try:
        for f in frames:
            c = time.process_time()
            tracker.process(f)
            total += time.process_time() - c
    finally:
        for owner, name, fn, own in wrapped:
            setattr(owner, name, fn) if own else delattr(owner, name)
        for owner, session in sessions:
            owner.session = session
    out = {"total": total, **spent}
    out["rest (tracker glue, smoothing)"] = total - sum(spent.get(k, 0.0) for k in ("detector", "shape", "pose"))
    out["networks"] = sum(spent.get(key, 0.0) for _, key in owners)
    out["glue"] = total - out["networks"]
    out = {k: round(1e3 * v / len(frames), 3) for k, v in out.items()}
    out["glue share"] = round(out["glue"] / out["total"], 3)
    return out


class _TimedSession:
    """An onnxruntime session whose run() adds the CPU time of the thread it runs on to spent[key]
    (a run on the detector's second thread is counted there, not twice)."""

    def __init__(self, session, key, spent):
        self.session, self.key, self.spent = session, key, spent
        self.lock = threading.Lock()

    def __getattr__(self, name):
        return getattr(self.session, name)

    def run(self, *args, **kwargs):
        c = time.thread_time()
        try:
            return self.session.run(*args, **kwargs)
        finally:
            with self.lock:
                self.spent[self.key] = self.spent.get(self.key, 0.0) + time.thread_time() - c


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
    p.add_argument("--videos", nargs="+", default=None,
                   help="clips (default: the demo clip and the data pack's two real clips where it is there)")
    p.add_argument("--repeat", type=int, default=1, help="passes over the frames per round (default %(default)s)")
    p.add_argument("--rounds", type=int, default=5,
                   help="matched comparison: rounds of ours then MediaPipe's, alternating (default %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads per network")
    p.add_argument("--in-turn", action="store_true",
                   help="no second thread: the finder, the side network and each crop read in turn on the "
                        "caller's thread (finder_beside off, DetNetRunner.beside off)")
    add_model_arguments(p)              # --detnet, --side-detnet, --finder, --iknet, --set: as handeval's
    p.add_argument("--max-hands", type=int, nargs="+", default=[1, 2],
                   help="maximum numbers of hands, each measured on both sides (default 1 2)")
    args = p.parse_args()
    settings = detector_settings(args.set or [])
    from handmocap.perception.detector import HandDetector
    from handmocap.runtime.frames import read_video
    from handmocap.perception.tracker import HandTracker

    videos = args.videos or default_videos()
    rows, table = matched(videos, args.max_hands, args, settings)
    max_hands = args.max_hands[0]
    frames = [f for _, f in zip(range(MAX_FRAMES), read_video(str(videos[0])))]
    from handmocap.perception.ik_solver import model_path
    results = {"matched": rows, "frames": len(frames), "load_avg": os.getloadavg()[0], "threads": args.threads,
               "video": str(videos[0]), "max_hands": max_hands, "iknet": str(model_path(args.iknet)),
               "settings": settings}

    tracker = HandTracker(detnet=args.detnet, side_detnet=args.side_detnet, finder=args.finder, iknet=args.iknet,
                          threads=args.threads, max_hands=max_hands, **settings)
    if args.in_turn:
        one_thread(tracker.detector)
    for f in frames:                   # warm-up pass, and the hand is tracked from here on
        tracker.process(f)
    passes = max(args.repeat, 3)       # the parts below: at least 3 passes each
    results["tracker"] = stats(timed(tracker.process, frames, passes))
    results["tracker"]["hands_per_frame"] = float(np.mean([len(tracker.process(f)) for f in frames]))
    results["tracker_stages_cpu_ms_per_frame"] = stage_cpu_ms(tracker, frames)

    det = HandDetector.load(args.detnet, args.finder, threads=args.threads, max_hands=max_hands,
                            side_detnet=args.side_detnet, **settings)
    if args.in_turn:
        one_thread(det)
    for f in frames:
        det.process(f)
    results["detector"] = stats(timed(det.process, frames, passes))
    results["detector"]["finder_runs_per_frame"] = det.stats["finder_runs"] / det.stats["frames"]

    crops = np.random.default_rng(0).integers(0, 255, (16, 128, 128, 3), np.uint8)
    one = stats(timed(lambda c: det.detnet(c[None]), list(crops), passes * 4))
    batch = stats(timed(det.detnet, [crops] * 10, passes))
    results["detnet_1_crop"] = {**one, "crops_per_s": 1e3 / one["median_ms"], "crops_per_cpu_s": 1e3 / one["median_cpu_ms"]}
    results["detnet_16_crops"] = {**batch, "crops_per_s": 16e3 / batch["median_ms"],
                                  "crops_per_cpu_s": 16e3 / batch["median_cpu_ms"]}
    results["finder"] = stats(timed(det.finder.find, frames[:30], passes))

    print(json.dumps(results, indent=1))
    print(table)


if __name__ == "__main__":
    main()
