"""What the slow frames carry: HandTracker.process's CPU time per frame, by what happened on it.

    python benchmarks/bench_frame_events.py [--videos V ...] [--max-hands 2] [--passes 3] [--in-turn] [--set KEY=VALUE ...]

For each video (default: the two-hand real clip of bench_tracker.py, or the demo clip where
the data pack is absent), `--passes` passes over its first MAX_FRAMES frames after a warm-up
pass; each frame's CPU time (time.process_time, every thread of the process) and wall time
(what the frame waits; below CPU where work runs on two cores at once, above it where the
machine is busy) and the detector's events on it, from the change of its `stats`:
a finder run, a new track, a track re-seeded from the finder's box, a track evicted by a
found hand, a found hand refused at birth (unborn), a mirror vote (a track's age a multiple of mirror_vote_every), a
second look, a side re-read, and the number of DetNet crops. Printed: p50 / p95 / p99 of all
frames, of the frames with each event and of the frames with none; how many frames carry
two periodic events at once; and what the slowest 10% of frames (wall time) carry against the rest.
--in-turn: one thread, as before session 39: the finder, the side network and each crop
read one after the other on the caller's thread (finder_beside off, DetNetRunner.beside off).
Issue 51's first item (spread the periodic work) is read here; the in-graph tail it makes is
benchmarks/bench_tail.py's.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_tracker import default_videos, one_thread  # noqa: E402
from handmocap.runtime.frames import read_video  # noqa: E402
from handmocap.training.eval_cli import add_model_arguments, model_paths  # noqa: E402
MAX_FRAMES = 300
EVENTS = ("finder", "new_track", "reseed", "eviction", "unborn", "mirror_vote", "second_look", "side_reread")


def frame_events(tracker, frames):
    """(CPU ms (F,), events {name: (F,) bool}, crops (F,), wall ms (F,)) of one pass over `frames`
    from a reset."""
    detector = tracker.detector
    tracker.reset()
    ms, wall, crops, events = [], [], [], {e: [] for e in EVENTS}
    for frame in frames:
        ages = [t.age for t in detector.tracks]
        before = dict(detector.stats)
        t0, w0 = time.process_time(), time.perf_counter()
        tracker.process(frame)
        ms.append((time.process_time() - t0) * 1e3)
        wall.append((time.perf_counter() - w0) * 1e3)
        d = {k: detector.stats[k] - before[k] for k in before}
        every = detector.mirror_vote_every
        events["finder"].append(d["finder_runs"] > 0)
        events["new_track"].append(any(t.age <= 1 for t in detector.tracks) and d["finder_runs"] > 0)
        events["reseed"].append(d["reseeds"] > 0)
        events["eviction"].append(d["evictions"] > 0)
        events["unborn"].append(d["unborn"] > 0)
        events["mirror_vote"].append(bool(every) and any(a % every == 0 and a > 0 for a in ages))
        events["second_look"].append(d["second_looks"] > 0)
        events["side_reread"].append(d["side_rereads"] > 0)
        crops.append(d["crops"])
    return np.array(ms), {k: np.array(v) for k, v in events.items()}, np.array(crops), np.array(wall)


def quantiles(x):
    return "–" if len(x) == 0 else " / ".join(f"{np.percentile(x, q):.1f}" for q in (50, 95, 99))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--videos", nargs="+", type=Path, default=None)
    p.add_argument("--max-hands", type=int, default=2)
    p.add_argument("--passes", type=int, default=3)
    p.add_argument("--in-turn", action="store_true", help="everything on the caller's thread (no second thread)")
    add_model_arguments(p)
    args = p.parse_args()
    from handmocap.perception.tracker import HandTracker
    tracker = HandTracker(**{**model_paths(args), "max_hands": args.max_hands})
    if args.in_turn:
        one_thread(tracker.detector)
    for video in args.videos or default_videos()[-1:]:      # the two-hand real clip, else the demo clip
        frames = read_video(video)[:MAX_FRAMES]
        frame_events(tracker, frames)                    # warm-up
        runs = [frame_events(tracker, frames) for _ in range(args.passes)]
        ms = np.concatenate([r[0] for r in runs])
        events = {k: np.concatenate([r[1][k] for r in runs]) for k in EVENTS}
        crops = np.concatenate([r[2] for r in runs])
        wall = np.concatenate([r[3] for r in runs])
        print(f"\n{video.name}, max hands {args.max_hands}, {len(frames)} frames x {args.passes} passes"
              f"{', in turn on one thread' if args.in_turn else ''}: "
              f"ms a frame p50 / p95 / p99")
        print("| frames | share | CPU ms | wall ms | crops a frame |\n|---|---|---|---|---|")
        print(f"| all | 100% | {quantiles(ms)} | {quantiles(wall)} | {crops.mean():.1f} |")
        for name in EVENTS:
            m = events[name]
            print(f"| with {name.replace('_', ' ')} | {m.mean():.1%} | {quantiles(ms[m])} | {quantiles(wall[m])} | "
                  f"{crops[m].mean() if m.any() else float('nan'):.1f} |")
        none = ~np.any([events[k] for k in EVENTS], axis=0)
        print(f"| with none of them | {none.mean():.1%} | {quantiles(ms[none])} | {quantiles(wall[none])} | "
              f"{crops[none].mean():.1f} |")
        periodic = np.sum([events[k] for k in ("finder", "mirror_vote")], axis=0)
        print(f"frames with a finder run and a mirror vote at once: {np.mean(periodic >= 2):.1%}")
        slow = wall >= np.percentile(wall, 90)
        print("slowest 10% of frames against the rest: "
              + ", ".join(f"{k.replace('_', ' ')} {events[k][slow].mean():.0%} / {events[k][~slow].mean():.0%}"
                          for k in EVENTS)
              + f"; crops {crops[slow].mean():.1f} / {crops[~slow].mean():.1f}")


if __name__ == "__main__":
    main()
