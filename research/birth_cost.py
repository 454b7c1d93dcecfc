"""What a new hand costs the frame it is found on: crops read and wall ms on the frames where
the detector made a new track, against every frame, for detector settings side by side
(session 52: DetNet's angle head reads a new hand at its own turn instead of at all four).

    python research/birth_cost.py runs/angle/detnet_lite0_int8.onnx "" turn_from_head=0.5,turn_tracked_from_head=false

The first argument is a DetNet file (with the int8 network's side, as `handeval --detnet F
--side-detnet int8`); each further argument one pipeline's comma-separated detector settings
("": the defaults). Over the held-back clips of video/wild, one pass each, frames as they are.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from handmocap.perception.detector import HandDetector
from handmocap.training import eval_cli
from handmocap.training import eval_people as ep
from handmocap.training import real_data


def main():
    detnet, pipelines = sys.argv[1], sys.argv[2:] or [""]
    clips = real_data.wild_clips(real_data.SHARED_DATA, held_back=True, drops=("wild",))
    print("| settings | frames | frames with a new track | crops on them, mean | ms on them, median (p90) | "
          "crops a frame, mean | ms a frame, median |")
    print("|---|---|---|---|---|---|---|")
    for settings in pipelines:
        detector = HandDetector.load(detnet, side_detnet="int8",
                                     **eval_cli.detector_settings([s for s in settings.split(",") if s]))
        birth, crops, ms = [], [], []
        for video in clips:
            detector.reset()
            fps = ep.clip_fps(video)
            for f, (image, _, _, _) in enumerate(ep.frames_of_clip(video)):
                made, read = detector.next_id, detector.stats["crops"]
                t = time.perf_counter()
                detector.process(image, f / fps)
                ms.append(1e3 * (time.perf_counter() - t))
                birth.append(detector.next_id > made)
                crops.append(detector.stats["crops"] - read)
        birth, crops, ms = np.array(birth), np.array(crops), np.array(ms)
        print(f"| {settings or 'default'} | {len(ms)} | {birth.sum()} | {crops[birth].mean():.2f} | "
              f"{np.median(ms[birth]):.1f} ({np.percentile(ms[birth], 90):.1f}) | {crops.mean():.2f} | "
              f"{np.median(ms):.1f} |", flush=True)


if __name__ == "__main__":
    main()
