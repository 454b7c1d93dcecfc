"""Where a tracker configuration's extra time goes: the stage table of `bench_tracker.py`
(`stage_cpu_ms`: CPU ms a frame of the whole frame, DetNet's runs, the side network's, the
finder's, IKNet's, and the glue), for several configurations in alternating rounds on the same
frames, with the DetNet runs and crops a frame. No MediaPipe: this compares configurations
with each other, which the matched bench's ratios (each run with its own MediaPipe rounds, ±0.1
on this machine) cannot resolve to a few percent.

    python research/config_cost.py --config default \
        --config "S: --detnet runs/detnet/s68_slim/int8.onnx --side-detnet int8 --set turn_by=palm --finder models/finder_lite0_int8.onnx" \
        [--videos V ...] [--max-hands 1] [--rounds 4]

A --config is "NAME: ARGUMENTS" (the tracker arguments of `bench_tracker.py` / `handeval`), or
`default`. Prints, per clip, each configuration's median over the rounds of each stage, and its
total against the first configuration's.
"""
import argparse
import shlex
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_tracker import MAX_FRAMES, default_videos, stage_cpu_ms  # noqa: E402

from handmocap.training.eval_cli import add_model_arguments, detector_settings  # noqa: E402

STAGES = ("total", "detector: DetNet network", "detector: side network", "detector: finder network",
          "pose: IKNet network", "glue")


def parse_config(text):
    """"NAME: ARGS" or "default" -> (name, argparse namespace of the tracker arguments)."""
    name, _, rest = text.partition(":")
    p = argparse.ArgumentParser()
    add_model_arguments(p)
    p.add_argument("--threads", type=int, default=1)
    return name.strip(), p.parse_args(shlex.split(rest))


class Counted:
    """An onnxruntime session that counts its runs and the crops (first input's batch) they read."""

    def __init__(self, session):
        self.session, self.runs, self.items = session, 0, 0

    def __getattr__(self, name):
        return getattr(self.session, name)

    def run(self, outputs, feeds, *args, **kwargs):
        self.runs += 1
        self.items += len(next(iter(feeds.values())))
        return self.session.run(outputs, feeds, *args, **kwargs)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", action="append", required=True, help='"NAME: ARGS" or default (repeat)')
    p.add_argument("--videos", nargs="+", default=None)
    p.add_argument("--max-hands", type=int, default=1)
    p.add_argument("--rounds", type=int, default=4)
    args = p.parse_args()
    from handmocap.perception.tracker import HandTracker
    from handmocap.runtime.frames import read_video
    configs = [parse_config(c) for c in args.config]
    for video in args.videos or default_videos():
        frames = [f for _, f in zip(range(MAX_FRAMES), read_video(str(video)))]
        trackers = {}
        for name, a in configs:
            t = HandTracker(detnet=a.detnet, side_detnet=a.side_detnet, finder=a.finder, iknet=a.iknet,
                            threads=a.threads, max_hands=args.max_hands, **detector_settings(a.set or []))
            for f in frames:                                    # warm-up: the hands tracked from here on
                t.process(f)
            trackers[name] = t
        got = {name: [] for name, _ in configs}
        counts = {}
        for _ in range(args.rounds):
            for name, t in trackers.items():                    # alternating: each round every configuration
                counter = Counted(t.detector.detnet.session)
                t.detector.detnet.session = counter
                got[name].append(stage_cpu_ms(t, frames))
                t.detector.detnet.session = counter.session
                counts[name] = (counter.runs / len(frames), counter.items / len(frames))
        print(f"\n{Path(video).name}, max hands {args.max_hands}, {len(frames)} frames, median of {args.rounds} rounds "
              f"(CPU ms a frame)\n| configuration | " + " | ".join(STAGES) + " | DetNet runs, crops a frame | total / first |")
        print("|---" * (len(STAGES) + 3) + "|")
        first = None
        for name, rows in got.items():
            med = {k: float(np.median([r.get(k, 0.0) for r in rows])) for k in STAGES}
            first = first or med["total"]
            print(f"| {name} | " + " | ".join(f"{med[k]:.2f}" for k in STAGES)
                  + f" | {counts[name][0]:.2f}, {counts[name][1]:.2f} | {med['total'] / first:.3f} |", flush=True)


if __name__ == "__main__":
    main()
