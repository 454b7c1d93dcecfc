"""shape: a running hand-shape estimate per track (paper Eq. 8). /hand/keypoints -> /hand/shape.

Per track id one ShapeTracker accumulates the bone lengths of the detector's normalized 3D
joints (bone lengths do not change under the mirroring of left hands); the fitted beta,
the rest pose of the model at that beta (root-relative, scale-normalized: IKNet's
reference input) and its bone ratios are published for every tracked hand with every
keypoints message, so a late subscriber has the shape at once (latched by repetition).
A track not seen for `forget_after_s` is dropped.
"""
from __future__ import annotations

import time

import numpy as np

from handmocap.hand_model import HandModel
from handmocap.node import Node, run
from handmocap.shape import ShapeFitter, ShapeTracker, bone_ratios
from handmocap.skeleton import normalize_joints

PARAMS = {"model": None, "forget_after_s": 2.0, "window": 600}


class ShapeEstimator:
    """Shape trackers of all live tracks; knows nothing of the bus."""

    def __init__(self, model: HandModel, forget_after_s: float = 2.0, window: int = 600):
        self.model = model
        self.fitter = ShapeFitter(model)
        self.forget_after_s = forget_after_s
        self.window = window
        self.tracks: dict[int, tuple[ShapeTracker, str, float]] = {}

    def update(self, hands: list[dict], now: float) -> list[dict]:
        """hands: HandKeypoints hands; returns HandShape shapes of every live track."""
        for h in hands:
            tracker = self.tracks.get(h["track_id"], (None,))[0] or ShapeTracker(self.fitter, window=self.window)
            tracker.update(h["xyz_rel"])
            self.tracks[h["track_id"]] = (tracker, h["handedness"], now)
        for tid in [t for t, (_, _, seen) in self.tracks.items() if now - seen > self.forget_after_s]:
            del self.tracks[tid]
        out = []
        for tid, (tracker, handedness, _) in sorted(self.tracks.items()):
            rest = normalize_joints(self.model.rest_joints(tracker.beta))
            out.append({"track_id": tid, "handedness": handedness,
                        "beta": tracker.beta.astype(np.float32),
                        "rest_xyz": rest.astype(np.float32),
                        "bone_ratios": bone_ratios(rest).astype(np.float32),
                        "samples": tracker.n_samples})
        return out


def main() -> None:
    node = Node("shape", params=PARAMS)
    p = node.params
    estimator = ShapeEstimator(HandModel.load(p["model"]), p["forget_after_s"], p["window"])
    node.subscribe("/hand/keypoints", "HandKeypoints", mode="all")
    node.advertise("/hand/shape", "HandShape")
    for msg in node:
        shapes = estimator.update(msg.data["hands"], time.monotonic())
        node.publish("/hand/shape", {"shapes": shapes}, stamp_ns=msg.stamp_ns,
                     frame_id=msg.data["header"]["frame_id"])
    node.close()


if __name__ == "__main__":
    run(main)
