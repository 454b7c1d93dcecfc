"""howiema 040's 2D mean error over ten runs: as the frames are and 9 more with every pixel moved
by -1/0/+1 (seeds 0-8), as `handeval people --jitter` does for the clips (session 51).

    python research/howiema_over_runs.py default runs/detnet/X/int8.onnx set:turn_check_below=0.6,turn_check_every=6
    python research/howiema_over_runs.py default runs/angle/detnet_lite0_int8.onnx,turn_from_head=0.5

Each argument is a pipeline: `default`, a DetNet file (read with int8's side, as `handeval
--detnet F --side-detnet int8`), `set:KEY=VALUE,...` detector settings on the default, or a
DetNet file and settings for it (`FILE,KEY=VALUE,...`). One
run of the split decides nothing when two networks differ by a few tenths of a pixel: the
finder's box and the crops move with the pixels. Session 51: the default 11.92 px (spread 0.30),
session 46's mean of two 12.03 (0.37).
"""
from __future__ import annotations

import json
import sys
import tempfile
import zlib
from pathlib import Path

import cv2
import numpy as np

from handmocap.training import eval_cli
from handmocap.training.eval_people import moved_pixels
from handmocap.training.real_data import SHARED_DATA

SPLIT = "howiema_040"


def pipeline(arg):
    """HandTracker keywords of one command-line argument."""
    if arg == "default":
        return {}
    if arg.startswith("set:"):
        return eval_cli.detector_settings(arg[4:].split(","))
    path, *settings = arg.split(",")
    return {"detnet": path, "side_detnet": "int8", **eval_cli.detector_settings(settings)}


def moved(files, seed, folder):
    """The split's images with every pixel moved by a seeded -1/0/+1, written to `folder`."""
    rng = np.random.default_rng([seed, zlib.crc32(SPLIT.encode())])
    folder.mkdir(parents=True, exist_ok=True)
    for path in files:
        cv2.imwrite(str(folder / path.name), moved_pixels(cv2.imread(str(path)), rng), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return folder


def main():
    pipelines = sys.argv[1:] or ["default"]
    work = Path(tempfile.gettempdir()) / "handeval" / SPLIT
    if not (work / "meta.json").is_file():
        eval_cli.SPLITS[SPLIT](SHARED_DATA, work)
    sequence = json.loads((work / "meta.json").read_text())["sequence"]
    with np.load(work / "gt.npz") as g:
        truth = {k: g[k] for k in g.files}
    files = sorted((work / "images").glob("*.png"))
    px = {name: [] for name in pipelines}
    with tempfile.TemporaryDirectory() as scratch:
        for seed in [None, *range(9)]:
            images = work / "images" if seed is None else moved(files, seed, Path(scratch) / str(seed))
            for name in pipelines:
                pred = eval_cli.predict(images, None, None, sequence=sequence, models=pipeline(name), log=lambda *a: None)
                px[name].append(eval_cli.score(pred, truth)["2d"]["mean_px"])
                print(f"{'as they are' if seed is None else f'seed {seed}'}, {name}: {px[name][-1]:.2f} px", flush=True)
    for name, runs in px.items():
        print(f"{name}: mean {np.mean(runs):.2f} px, spread {np.ptp(runs):.2f}")


if __name__ == "__main__":
    main()
