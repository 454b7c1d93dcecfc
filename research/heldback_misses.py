"""Where one held-back clip's hands go unfound: per MediaPipe hand, whether the finder's box lies on it
(IoU > 0.3 at its threshold) and whether the detector output one on it.

    python research/heldback_misses.py CLIP     # e.g. klyct__limpiar
"""
import sys
from handmocap.training import real_data, eval_people
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.crops import square_box
from handmocap.perception.detector import HandDetector
from handmocap.perception.hand_finder import box_iou

name = sys.argv[1]
video = [v for v in real_data.wild_clips(SHARED_DATA, held_back=True) if v.stem == name][0]
det = HandDetector.load()
finder = det.finder
c = {"labels": 0, "found": 0, "finder_on": 0, "finder_on_missed": 0, "missed": 0, "frames_2mp": 0, "ours_when_2mp": 0}
for f, (img, hands, rel, sides) in enumerate(eval_people.frames_of_clip(video)):
    out = det.process(img)
    boxes = finder.find(img, det.finder_threshold, 4)
    near = [eval_people.nearest_label(h["uv"], hands) for h in out]
    hit = {k for k, d in near if d < eval_people.ON_HAND}
    if len(hands) == 2:
        c["frames_2mp"] += 1; c["ours_when_2mp"] += len(out)
    for k, lab in enumerate(hands):
        c["labels"] += 1
        on = any(box_iou(square_box(lab), b.box)[0, 0] > 0.3 for b in boxes)
        c["finder_on"] += on
        if k in hit:
            c["found"] += 1
        else:
            c["missed"] += 1; c["finder_on_missed"] += on
    if f % 20 == 0:
        print(f, len(hands), "ours", len(out), "finder", [round(float(b.score), 2) for b in boxes],
              "hit", sorted(hit), "finder runs", det.stats["finder_runs"], "unborn", det.stats["unborn"])
print(c)
print({k: v for k, v in det.stats.items()})
