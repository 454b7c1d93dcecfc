"""How often the finder runs beside tracking, and what it costs (issue 47, "births that cost
little"): the default detector over the held-back clips of both drops, per finder file.

    python research/finder_cost.py [models/finder.onnx models/finder_lite0_int8.onnx]

Per finder: the share of frames with a finder run, its median and p90 ms a run (wall, one
onnxruntime thread, HandFinder.find wrapped in a timer), and the finder's ms per frame
averaged over all frames (what it adds to a frame on average).
"""
import sys
import time

import numpy as np

from handmocap.perception.detector import HandDetector
from handmocap.training import eval_people, real_data


def main():
    finders = sys.argv[1:] or ["models/finder.onnx", "models/finder_lite0_int8.onnx"]
    clips = real_data.wild_clips(held_back=True, drops=real_data.WILD_DROPS)
    print("| finder | frames | frames with a finder run | ms a run, median (p90) | finder ms a frame, mean |\n"
          "|---|---|---|---|---|")
    for path in finders:
        det = HandDetector.load(finder=path)
        spent, run = [], det.finder.find

        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return run(*args, **kwargs)
            finally:
                spent.append((time.perf_counter() - t) * 1e3)
        det.finder.find = timed
        frames = 0
        for video in clips:
            det.reset()
            for f, (image, *_labels) in enumerate(eval_people.frames_of_clip(video)):
                det.process(image, f / eval_people.clip_fps(video))
                frames += 1
        spent = np.array(spent)
        print(f"| {path} | {frames} | {len(spent) / frames:.1%} | {np.median(spent):.2f} ({np.percentile(spent, 90):.2f}) "
              f"| {spent.sum() / frames:.2f} |")


if __name__ == "__main__":
    main()
