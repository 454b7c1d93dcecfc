"""Per track of one held-back clip: its frames, how many of them it is published as MediaPipe's side,
its mean position and mean heatmap peak.

    python research/heldback_side_tracks.py CLIP [DETNET.onnx]     # e.g. rodrmilano00__ROSA
"""
import sys, collections
import numpy as np
from handmocap.training import real_data, eval_people
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.detector import HandDetector
name = sys.argv[1]
det = HandDetector.load(**({"detnet_path": sys.argv[2]} if len(sys.argv) > 2 else {}))
video = [v for v in real_data.wild_clips(SHARED_DATA, held_back=True) if v.stem == name][0]
tr = collections.defaultdict(lambda: {"n": 0, "right": 0, "lab": collections.Counter(), "x": [], "conf": []})
for f, (img, hands, rel, sides) in enumerate(eval_people.frames_of_clip(video)):
    for h in det.process(img):
        k, d = eval_people.nearest_label(h["uv"], hands)
        if d >= eval_people.ON_HAND: continue
        t = tr[h["track_id"]]; t["n"] += 1; t["right"] += h["handedness"] == sides[k]; t["lab"][sides[k]] += 1
        t["x"].append(h["uv"][:, 0].mean() / img.shape[1]); t["conf"].append(float(np.mean(h["confidence"])))
for tid, t in tr.items():
    print(tid, "frames", t["n"], "side right", t["right"], "labels", dict(t["lab"]), "x %.2f" % np.mean(t["x"]), "peak %.2f" % np.mean(t["conf"]))
