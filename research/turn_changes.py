"""How often tracked crops change their quarter turn, and the clip's median error, for detector
settings side by side (session 52: DetNet's angle head turned crops far more often than the
joints did).

    python research/turn_changes.py runs/angle/detnet_lite0_int8.onnx rodrmilano00__ROSA \\
        --set "" turn_from_head=0.5,turn_head_margin=45 turn_from_head=0.5

The first argument is a DetNet file (read with the int8 network's side, as `handeval --detnet F
--side-detnet int8`); then held-back video/wild clips by name; each `--set` value is one
pipeline's comma-separated detector settings ("" : the file with the default settings). Printed
per clip and pipeline: the turn changes (a track's crop angle differing from its last frame's),
the scored hands (on MediaPipe's reliable hands, as `handeval people` scores) and their median
error / hand size (one run, frames as they are).
Session 52, `rodrmilano00__ROSA`: 4 changes, median 0.140 (default settings); 100, 0.218 (the head,
margin 45); 77, 0.162 (margin 60).
"""
from __future__ import annotations

import argparse

import numpy as np

from handmocap.perception.crops import angle_apart
from handmocap.perception.detector import HandDetector
from handmocap.training import eval_cli
from handmocap.training import eval_people as ep
from handmocap.training import real_data


def turn_changes(detector, video):
    """(turn changes, errors / hand size of the scored hands) of one clip tracked by `detector`."""
    last, changes, errors = {}, 0, []
    for _, scored in ep.scored_hands(detector, video):
        errors += [np.linalg.norm(h["uv"] - label, axis=-1).mean() / real_data.hand_size(label) for h, label, _, _ in scored]
        for t in detector.tracks:
            changes += t.track_id in last and angle_apart(t.crop.angle, last[t.track_id]) > 0.1
            last[t.track_id] = t.crop.angle
    return changes, errors


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("detnet", help="a DetNet file")
    p.add_argument("clips", nargs="+", help="held-back video/wild clip names")
    p.add_argument("--set", nargs="+", default=[""], help="one pipeline's settings each, KEY=VALUE,...")
    args = p.parse_args()
    videos = {v.stem: v for v in real_data.wild_clips(real_data.SHARED_DATA, held_back=True, drops=("wild",))}
    print("| clip | settings | turn changes | scored hands | median error / hand size |")
    print("|---|---|---|---|---|")
    for name in args.clips:
        if name not in videos:
            raise SystemExit(f"{name}: not a held-back video/wild clip ({', '.join(sorted(videos))})")
        for settings in args.set:
            keywords = eval_cli.detector_settings([s for s in settings.split(",") if s])
            detector = HandDetector.load(args.detnet, side_detnet="int8", **keywords)
            changes, errors = turn_changes(detector, videos[name])
            print(f"| {name} | {settings or 'default'} | {changes} | {len(errors)} | {np.median(errors):.3f} |", flush=True)


if __name__ == "__main__":
    main()
