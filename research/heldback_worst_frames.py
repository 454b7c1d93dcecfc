"""The shipped detector's worst-read hands of one held-back clip, drawn: ours red, MediaPipe's green.

    python research/heldback_worst_frames.py CLIP    # e.g. Kirichovka__want -> runs/worst_CLIP.png
"""
import sys
from pathlib import Path
import cv2, numpy as np
from handmocap.training import real_data, eval_people
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.detector import HandDetector
from handmocap.perception.skeleton import BONES

name = sys.argv[1]
video = [v for v in real_data.wild_clips(SHARED_DATA, held_back=True) if v.stem == name][0]
det = HandDetector.load()
rows = []
for f, (img, hands, rel, sides) in enumerate(eval_people.frames_of_clip(video)):
    out = det.process(img)
    for h in out:
        k, d = eval_people.nearest_label(h["uv"], hands)
        if d < eval_people.ON_HAND and rel[k]:
            e = np.linalg.norm(h["uv"] - hands[k], axis=-1).mean() / real_data.hand_size(hands[k])
            rows.append((e, f, h["uv"].copy(), hands[k].copy(), h["handedness"], sides[k], img.copy()))
rows.sort(key=lambda r: -r[0])
errs = np.array([r[0] for r in rows]); print(name, len(rows), "median", np.median(errs))
tiles = []
pick = rows[::max(1, len(rows) // 12)][:12]
for e, f, uv, gt, side, gside, img in pick:
    c = np.concatenate([uv, gt]).mean(0); s = max(np.ptp(gt, 0).max() * 2.2, 60)
    x0, y0 = int(c[0] - s / 2), int(c[1] - s / 2)
    for pts, col in ((gt, (0, 255, 0)), (uv, (0, 0, 255))):
        for a, b in BONES:
            cv2.line(img, tuple(np.int32(pts[a])), tuple(np.int32(pts[b])), col, 2)
        cv2.circle(img, tuple(np.int32(pts[4])), 4, col, -1)
    pad = cv2.copyMakeBorder(img, 400, 400, 400, 400, cv2.BORDER_CONSTANT)
    tile = cv2.resize(pad[y0 + 400:y0 + 400 + int(s), x0 + 400:x0 + 400 + int(s)], (256, 256))
    cv2.putText(tile, f"f{f} e{e:.2f} {side[0]}/{gside[0]}", (4, 16), 0, 0.5, (255, 255, 255), 1)
    tiles.append(tile)
while len(tiles) % 4: tiles.append(np.zeros_like(tiles[0]))
grid = np.vstack([np.hstack(tiles[i:i + 4]) for i in range(0, len(tiles), 4)])
Path("runs").mkdir(exist_ok=True)
cv2.imwrite(f"runs/worst_{name}.png", grid)
print(f"wrote runs/worst_{name}.png")
