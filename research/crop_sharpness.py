"""Do the real training crops' soft pixels matter? DetNet on held-back hands' crops cut around
MediaPipe's label from the frame as it is, and from the frame softened to the detail a real
training crop carries (session 58).

    python research/crop_sharpness.py [--drops wild]

The real-crop cache keeps each hand in a context crop of detnet_data.CTX px (176) over
CTX_SCALE (2.4) times its keypoint box, and a training crop (1.3 times the box) is cut from that:
about CTX_CROP_SIDE = 95 context px resampled to 128, where the tracker cuts its crop from the
frame at full detail (a median 160 frame px on video/wild's held-back clips). Here each crop is
read as cut, and again from the frame shrunk by CTX_CROP_SIDE / crop side (INTER_AREA) and
enlarged back (linear): the detail the network was trained on.

Session 58, shipped networks, video/wild held back (2,282 hands, 89% of their crops over 95 px):
median 0.0792 as cut, 0.0833 softened (crops over 142 px: 0.0536 against 0.0555). The network
reads sharp crops better: the soft training crops are no gap to close.
"""
from __future__ import annotations

import argparse

import cv2
import numpy as np

from handmocap.perception.crops import crop_for_joints
from handmocap.perception.detector import HandDetector
from handmocap.training import eval_people as ep
from handmocap.training import real_data
from handmocap.training.detnet_data import CTX_CROP_SIDE


def softened(image, factor):
    """The frame at `factor` (< 1) of its detail, at its own size."""
    small = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_LINEAR)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--drops", default="wild", help="comma-separated: wild, wild3")
    args = p.parse_args()
    det = HandDetector.load()
    rows = []
    for video in real_data.wild_clips(real_data.SHARED_DATA, held_back=True, drops=tuple(args.drops.split(","))):
        for image, scored in ep.scored_hands(det, video):
            for hand, label, _, _ in scored:
                crop = crop_for_joints(label, hand["handedness"] == "left", det.crop_scale, det.upright_step,
                                       det.crop_size)
                factor = min(1.0, CTX_CROP_SIDE / crop.side)
                reads = [det._run(image, [crop], read_side=False)["uv"][0]]
                reads.append(det._run(softened(image, factor), [crop], read_side=False)["uv"][0] if factor < 1 else reads[0])
                size = real_data.hand_size(label)
                rows.append([crop.side] + [np.linalg.norm(crop.to_frame(uv) - label, axis=-1).mean() / size
                                           for uv in reads])
    r = np.asarray(rows)
    big = r[:, 0] > 1.5 * CTX_CROP_SIDE
    print(f"{len(r)} hands; crop side median {np.median(r[:, 0]):.0f} px, over {CTX_CROP_SIDE:.0f} px: "
          f"{100 * np.mean(r[:, 0] > CTX_CROP_SIDE):.0f}%")
    print(f"median error / hand size: as cut {np.median(r[:, 1]):.4f}, softened {np.median(r[:, 2]):.4f}; "
          f"crops over {1.5 * CTX_CROP_SIDE:.0f} px ({big.sum()}): {np.median(r[big, 1]):.4f} against {np.median(r[big, 2]):.4f}")


if __name__ == "__main__":
    main()
