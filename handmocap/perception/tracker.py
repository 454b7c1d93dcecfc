"""HandTracker: the whole image-to-pose pipeline in one process, like MediaPipe's HandLandmarker.

    tracker = HandTracker()                          # models/detnet_lite0_int8.onnx (+ detnet_int8's side), finder.onnx, iknet_int8.onnx
                                                     # (grey frames: finder_grey.onnx, detnet_grey_int8.onnx)
    for frame in frames:
        hands = tracker.process(frame_bgr, K=None, stamp_ns=None)
        # each hand: track_id, handedness, score, xyz (21,3) m camera frame, root (3,),
        # quat (21,4), pose (16,3), beta (10,), uv (21,2) px, translation_valid,
        # and xyz_rel (21,3) (DetNet's normalized joints), vertices (V,3) m when asked

Stages, the same code as the graph's nodes: detector.HandDetector (finder, crops, DetNet,
tracks) -> shape.ShapeEstimator (paper Eq. 8, one ShapeTracker per track) ->
pose.PoseEstimator (IKNet, FK at the track's beta, One Euro smoothing, Eq. 5
translation). K: (3,3) or (4,) fx, fy, cx, cy of the frame; without it
camera_info.default_K (a DEFAULT_HFOV_DEG = 60 degree horizontal field of view, principal
point at the centre). stamp_ns: capture time (smoothing needs real time between frames;
default: frame count / `fps`).
"""
from __future__ import annotations

import numpy as np

from handmocap.perception import camera_info
from handmocap.perception.detector import HandDetector
from handmocap.perception.hand_model import HandModel
from handmocap.perception.ik_solver import IKSolver
from handmocap.perception.pose import PoseEstimator
from handmocap.perception.shape import ShapeEstimator
from handmocap.perception.skeleton import DEFAULT_HAND_LENGTH_M, ROOT


class HandTracker:
    """detnet, finder, iknet, model: paths (None: the bundled ones; finder "none": no
    finder, the centre square is tried instead; iknet "float32": the float32 IKNet instead
    of the default static int8 copy); side_detnet: the DetNet whose handedness head gives
    the side (None: int8's for the default detnet, else detnet's own; "none": detnet's own); detector: a ready HandDetector instead of
    detnet/finder. smooth: One Euro smoothing of rotations and translation per track, and
    of the 2D joints unless smooth_min_cutoff is given (off for single images). vertices:
    add each hand's mesh vertices (V,3) m camera frame. Other keywords go to HandDetector
    (max_hands, presence_threshold, min_confidence, birth_confidence, redetect_every,
    crop_scale, fallback, ...). For unrelated photos: reset() before each, and
    `HandTracker(**detector.PHOTO_SETTINGS)`: birth_confidence 0 (the default 0.3 is for video,
    where a doubtful hand gets another chance next frame), the centre square tried where
    the finder found nothing (a close-up) and each hand read on 4 variants of its crop as
    well (test_time_crops), as `handeval predict` does."""

    def __init__(self, detnet=None, finder=None, iknet=None, model=None, threads=1, smooth=True,
                 vertices=False, fps=30.0, clamp_to_limits=True, hand_length=DEFAULT_HAND_LENGTH_M, detector=None,
                 side_detnet=None, **detector_kwargs):
        self.model = HandModel.load(model)
        if not smooth:
            detector_kwargs.setdefault("smooth_min_cutoff", None)    # nor the 2D joints
        self.detector = detector or HandDetector.load(detnet, finder, threads=threads, side_detnet=side_detnet,
                                                      **detector_kwargs)
        self.shapes = ShapeEstimator(self.model)
        self.poses = PoseEstimator(IKSolver.load(iknet, threads=threads, model=self.model), self.model,
                                   smooth=smooth, clamp_to_limits=clamp_to_limits, hand_length=hand_length)
        self.vertices, self.fps = vertices, fps
        self.frame_index = 0
        self.last_keypoints = []

    def reset(self):
        """Forget every track (call between unrelated images or videos)."""
        self.detector.reset()
        self.shapes.tracks.clear()
        self.poses.tracks.clear()
        self.poses.shapes = {}

    def process(self, image_bgr, K=None, stamp_ns=None):
        """Hands of one BGR frame (H,W,3) uint8: list of dicts with the HandPose fields."""
        h, w = image_bgr.shape[:2]
        K = camera_info.default_K(w, h) if K is None else camera_info.as_K(K)
        t = self.frame_index / self.fps if stamp_ns is None else stamp_ns / 1e9
        self.frame_index += 1
        keypoints = self.detector.process(image_bgr, t)
        self.last_keypoints = keypoints
        self.poses.set_shapes(self.shapes.update(keypoints, t))
        hands = self.poses.update(keypoints, K, t)
        by_id = {k["track_id"]: k for k in keypoints}
        for hand in hands:
            hand["xyz_rel"] = by_id[hand["track_id"]]["xyz_rel"]
            if self.vertices:
                verts, joints = self.model.forward(hand["quat"].astype(np.float64), hand["beta"].astype(np.float64),
                                                   hand["handedness"])
                hand["vertices"] = (verts - joints[ROOT] + hand["root"]).astype(np.float32)
        return hands
