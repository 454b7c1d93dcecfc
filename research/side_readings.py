"""How a track's side readings add up, and what other sums would have said (issue 46's side: >= 92%
tracked on the held-back clips, 85.6% in session 53).

    python research/side_readings.py models/detnet_lite0_int8.onnx [--clips NAME ...]

Tracks the held-back video/wild clips once (frames as they are) with the default pipeline (the
DetNet file read with the int8 network's side, as `handeval people --detnet F --side-detnet int8`)
and logs every side reading a track takes (`Track.add_handedness`: the head's readings, mirror
votes, the finder's) with the track's age. A scored hand (on MediaPipe's reliable hands, as
`handeval people` scores) keeps its track, age and MediaPipe's side. Then each sum below is replayed
over the same readings, and its side at each scored hand's frame is checked:

- "running mean": the tracker's own (a mean of logits clipped to +-HANDEDNESS_LOGIT_BOUND over
  the last HANDEDNESS_MEMORY readings); replayed, it must give the published side (printed as a
  check);
- the same with the logits clipped to +-C, or over all of the track's readings;
- "votes": each reading one vote (its sign), over the same memory.

A replay is only a sketch of what the tracker would do: the side a track holds chooses whether
its crop is mirrored, and the next readings are read on that crop. Prints per clip and pooled.
"""
from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np

from handmocap.perception import tracks as tracks_module
from handmocap.perception.detector import HandDetector
from handmocap.perception.tracks import HANDEDNESS_LOGIT_BOUND, HANDEDNESS_MEMORY, logit
from handmocap.training import eval_people as ep
from handmocap.training import real_data


def logged_clip(detector, video):
    """Track `video`; return [(track id, age at the frame, label is right, published is right)] of the
    scored hands (main's patched Track logs the readings meanwhile)."""
    scored = []
    for _, hands in ep.scored_hands(detector, video):
        ages = {t.track_id: t.age for t in detector.tracks}
        scored += [(h["track_id"], ages[h["track_id"]], side == "right", h["handedness"] == "right")
                   for h, _, _, side in hands]
    return scored


def running_mean(readings, age, clip=HANDEDNESS_LOGIT_BOUND, memory=HANDEDNESS_MEMORY):
    """The tracker's sum of one track's readings [(age, p_right, weight)] taken up to `age`
    (`Track.add_handedness`, with its bound and memory as arguments)."""
    value, samples = 0.0, 0.0
    for a, p, w in readings:
        if a > age:
            break
        n = min(samples + w, memory)
        value += (float(np.clip(logit(p), -clip, clip)) - value) * w / n
        samples = n
    return value >= 0.0


def votes(readings, age, memory=HANDEDNESS_MEMORY):
    """The sign of the sum of the last `memory` readings' weighted votes."""
    kept = [w * np.sign(logit(p)) for a, p, w in readings if a <= age][-memory:]
    return sum(kept) >= 0.0


SUMS = {
    "running mean (tracker's)": running_mean,
    "clip +-3": lambda r, a: running_mean(r, a, clip=3.0),
    "clip +-1.5": lambda r, a: running_mean(r, a, clip=1.5),
    "all readings": lambda r, a: running_mean(r, a, memory=10 ** 9),
    "all readings, clip +-1.5": lambda r, a: running_mean(r, a, clip=1.5, memory=10 ** 9),
    "votes": votes,
}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("detnet", help="a DetNet file")
    p.add_argument("--clips", nargs="*", help="held-back video/wild clip names (default: all)")
    args = p.parse_args()
    videos = real_data.wild_clips(real_data.SHARED_DATA, held_back=True, drops=("wild",))
    videos = [v for v in videos if not args.clips or v.stem in args.clips]

    log = defaultdict(list)             # track id -> [(age, p_right, weight)] of the clip being tracked
    original = tracks_module.Track.add_handedness

    def add_handedness(track, p_right, weight=1.0):      # the reading as the track takes it, then taken
        if not track.fixed_side:
            log[track.track_id].append((track.age, float(p_right), float(weight)))
        original(track, p_right, weight)

    tracks_module.Track.add_handedness = add_handedness
    detector = HandDetector.load(args.detnet, side_detnet="int8")
    right = defaultdict(lambda: defaultdict(list))     # sum name -> clip -> [right?]
    print("| clip | scored hands | " + " | ".join(SUMS) + " | published |")
    print("|---|---|" + "---|" * (len(SUMS) + 1))
    for video in videos:
        log.clear()
        scored = logged_clip(detector, video)
        for name, fn in SUMS.items():
            right[name][video.stem] = [fn(log[tid], age) == label for tid, age, label, _ in scored]
        right["published"][video.stem] = [pub == label for _, _, label, pub in scored]
        row = [f"{100 * np.mean(right[n][video.stem]):.1f}" for n in list(SUMS) + ["published"]]
        print(f"| {video.stem} | {len(scored)} | " + " | ".join(row) + " |", flush=True)
    pooled = [f"{100 * np.mean(sum(right[n].values(), [])):.1f}" for n in list(SUMS) + ["published"]]
    print(f"| **pooled** | {sum(len(v) for v in right['published'].values())} | " + " | ".join(pooled) + " |")


if __name__ == "__main__":
    main()
