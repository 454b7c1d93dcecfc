"""HandTracker in one process, no graph: a video's hands, then photos' hands.

    python examples/in_process.py [VIDEO] [PHOTO ...]
"""
import sys

import cv2

from handmocap import HandTracker
from handmocap.perception.detector import PHOTO_SETTINGS

video_path = sys.argv[1] if len(sys.argv) > 1 else "data/demo/hand_clip.mp4"
video = HandTracker()                        # a video or camera stream: tracks and smooths
# HandTracker(**ACCURATE_VIDEO_SETTINGS) (handmocap.perception.detector): each hand read on five crops a
# frame: 12-17% lower median 2D error for ~2.3x the time (detector node: tracked_test_time_crops 4)
# HandTracker(handedness="right"): only that hand is filmed; every hand is read as that side, so
# no handedness mistakes (detector node: handedness; webcam.yaml hand:=right)
cap = cv2.VideoCapture(video_path)
ok, frame = cap.read()
if not ok:
    sys.exit(f"{video_path}: no frame could be read (a missing file, or not a video OpenCV reads)")
while ok:
    for hand in video.process(frame, K=None):    # K (3,3) px; None: a 60° horizontal field of view
        print("video", hand["track_id"], hand["handedness"], "root_m", hand["root"].round(3))
    ok, frame = cap.read()

photos = HandTracker(smooth=False, **PHOTO_SETTINGS)  # unrelated photos: one chance each,
for path in sys.argv[2:]:                             # close-ups tried on the centre square
    photo = cv2.imread(path)
    if photo is None:
        sys.exit(f"{path}: not an image OpenCV reads (a missing file, or another format)")
    photos.reset()
    for hand in photos.process(photo):
        print("photo", path, hand["handedness"], "uv_px", hand["uv"][0].round(1))
