"""The hand finder's side on the held-back clips: how often its right_prob says MediaPipe's side.

    python research/finder_side_heldback.py [--training-clips] [--every 3]

Every 3rd frame of each held-back clip (or of the training people's clips: the finder
trained on those), the finder's boxes (threshold 0.2, up to 4) whose centre lies within
half the hand's size of a MediaPipe hand's joint-box centre; "right" when right_prob > 0.5
says that hand's label. One row per clip and the total.
"""
import argparse

import numpy as np

from handmocap.perception.hand_finder import HandFinder
from handmocap.training import eval_people, real_data
from handmocap.training.pose_data import SHARED_DATA


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--training-clips", action="store_true")
    p.add_argument("--every", type=int, default=3)
    args = p.parse_args()
    finder = HandFinder.load(threads=2)
    total = [0, 0]
    for video in real_data.wild_clips(SHARED_DATA, held_back=not args.training_clips):
        n = right = 0
        for f, (image, hands, _, sides) in enumerate(eval_people.frames_of_clip(video)):
            if f % args.every or not len(hands):
                continue
            centres = (hands.min(1) + hands.max(1)) / 2
            for box in finder.find(image, threshold=0.2, max_hands=4):
                dist = np.linalg.norm(centres - (box.box[:2] + box.box[2:]) / 2, axis=1) / real_data.hand_size(hands)
                k = int(np.argmin(dist))
                if dist[k] < eval_people.ON_HAND:
                    n += 1
                    right += (box.right_prob > 0.5) == (sides[k] == "right")
        total[0] += n
        total[1] += right
        print(f"{video.stem:32s} {right}/{n} = {right / max(n, 1):.1%}", flush=True)
    print(f"{'all':32s} {total[1]}/{total[0]} = {total[1] / max(total[0], 1):.1%}")


if __name__ == "__main__":
    main()
