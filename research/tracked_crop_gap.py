"""Where the tracked crops lose against crops cut around the label: the scored held-back hands
split by how their tracked crop differs from the label's (turn, side, centre), with the tracked
error and the error DetNet reads on the label's crop for the same hands (session 58).

    python research/tracked_crop_gap.py [--drops wild]

Session 58, shipped networks, video/wild held back (2,273 hands): tracked median 0.0956, on the
label's crop 0.0795. Hands whose crop is turned 45 degrees or more off the label's (22.8%):
0.252 tracked, 0.152 on the label's crop; the others 0.063 and 0.063. Crops within 0.8-1.25x the
label's side, centred within 0.15 of it and turned within 45 degrees (66%): 0.051 and 0.050. The
gap is the hands on a wrong turn, and those are hard on any crop.
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from handmocap.perception.crops import crop_for_joints
from handmocap.perception.detector import HandDetector
from handmocap.training import eval_people as ep
from handmocap.training import real_data


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--drops", default="wild", help="comma-separated: wild, wild3")
    args = p.parse_args()
    det = HandDetector.load()
    rows = []   # tracked error, label crop's error, side ratio, centre offset / side, turn apart (deg)
    for video in real_data.wild_clips(real_data.SHARED_DATA, held_back=True, drops=tuple(args.drops.split(","))):
        for image, scored in ep.scored_hands(det, video):
            for hand, label, crop, _ in scored:
                if crop is None:            # a track new on this frame: its crop was the finder's
                    continue
                ideal = crop_for_joints(label, hand["handedness"] == "left", det.crop_scale, det.upright_step,
                                        det.crop_size)
                size = real_data.hand_size(label)
                uv = ideal.to_frame(det._run(image, [ideal], read_side=False)["uv"][0])
                rows.append((np.linalg.norm(hand["uv"] - label, axis=-1).mean() / size,
                             np.linalg.norm(uv - label, axis=-1).mean() / size, crop.side / ideal.side,
                             np.linalg.norm(crop.centre - ideal.centre) / ideal.side,
                             abs(math.degrees(math.remainder(crop.angle - ideal.angle, 2 * math.pi)))))
    r = np.asarray(rows)
    print(f"{len(r)} hands: tracked median {np.median(r[:, 0]):.4f}, on the label's crop {np.median(r[:, 1]):.4f}")
    close = (r[:, 4] < 45) & (r[:, 2] >= 0.8) & (r[:, 2] <= 1.25) & (r[:, 3] <= 0.15)
    for name, mask in (("turned >= 45 deg off", r[:, 4] >= 45), ("turned < 45 deg off", r[:, 4] < 45),
                       ("side < 0.8x", r[:, 2] < 0.8), ("side 0.8-1.25x", (r[:, 2] >= 0.8) & (r[:, 2] <= 1.25)),
                       ("side > 1.25x", r[:, 2] > 1.25), ("centre off > 0.15 side", r[:, 3] > 0.15),
                       ("all of it close", close), ("not all close", ~close)):
        print(f"{name:24s} {100 * mask.mean():5.1f}% of hands: tracked {np.median(r[mask, 0]):.4f}, "
              f"on the label's crop {np.median(r[mask, 1]):.4f}")


if __name__ == "__main__":
    main()
