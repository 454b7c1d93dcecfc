"""Finder recall of MediaPipe's hands on video/wild clips: the whole frame vs the whole frame and every
tile window (needs research/finder_tiles.patch applied: `git apply research/finder_tiles.patch`).

    python research/finder_tiles_recall.py train|held TILES [THRESHOLD]
"""
import sys
import numpy as np
from handmocap.training import real_data, eval_people
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.hand_finder import HandFinder, box_iou, tile_windows
from handmocap.perception.crops import square_box
held = sys.argv[1] == "held"
tiles = int(sys.argv[2]); thr = float(sys.argv[3]) if len(sys.argv) > 3 else 0.3
finder = HandFinder.load()
tot = np.zeros(4)
for video in real_data.wild_clips(SHARED_DATA, held_back=held):
    c = np.zeros(4)   # labels, whole, whole-or-tile, false tile boxes
    for f, (img, hands, rel, sides) in enumerate(eval_people.frames_of_clip(video)):
        if f % 3: continue
        whole = [b.box for b in finder.find(img, 0.3, 2)]
        tb = [b.box for w in tile_windows(*img.shape[:2], tiles) for b in finder.find_in_window(img, w, thr, 2)]
        labs = [square_box(l) for l in hands]
        for lb in labs:
            c[0] += 1
            c[1] += any(box_iou(lb, b)[0, 0] > 0.3 for b in whole)
            c[2] += any(box_iou(lb, b)[0, 0] > 0.3 for b in whole + tb)
        c[3] += sum(not any(box_iou(lb, b)[0, 0] > 0.1 for lb in labs) for b in tb)
    tot += c
    print(f"{video.stem:40s} labels {c[0]:.0f} whole {c[1]/max(c[0],1):.1%} +tiles {c[2]/max(c[0],1):.1%} false tile boxes {c[3]:.0f}", flush=True)
print("total", tot, tot[1]/tot[0], tot[2]/tot[0])
