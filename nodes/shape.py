"""shape: a running hand-shape estimate per track (paper Eq. 8). /hand/keypoints -> /hand/shape.

A thin loop over handmocap.perception.shape.ShapeEstimator.

Per track id one ShapeTracker accumulates the bone lengths of the detector's normalized 3D
joints (bone lengths do not change under the mirroring of left hands); the fitted beta,
the rest pose of the model at that beta (root-relative, scale-normalized: IKNet's
reference input) and its bone ratios are published for every tracked hand with every
keypoints message, so a late subscriber has the shape at once (latched by repetition).
A track not seen for `forget_after_s` is dropped.
"""
from __future__ import annotations

import time
from typing import Callable

from handmocap.perception.hand_model import HandModel
from handmocap.runtime.node import Message, Node, check_file_param, check_number_param, run, spin
from handmocap.perception.shape import ShapeEstimator

PARAMS = {"model": None, "forget_after_s": 2.0, "window": 600}


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param)."""
    check_file_param("shape", "model", params.get("model"))
    check_number_param("shape", "forget_after_s", params.get("forget_after_s", PARAMS["forget_after_s"]),
                       positive=True)
    check_number_param("shape", "window", params.get("window", PARAMS["window"]), minimum=1, integer=True)


def start() -> tuple[Node, Callable[[Message], None]]:
    """The node, set up, and its handler of one /hand/keypoints message."""
    node = Node("shape", params=PARAMS)
    p = node.params
    estimator = ShapeEstimator(HandModel.load(p["model"]), p["forget_after_s"], p["window"])
    node.subscribe("/hand/keypoints", "HandKeypoints", mode="all")
    node.advertise("/hand/shape", "HandShape")

    def on_keypoints(msg: Message) -> None:
        shapes = estimator.update(msg.data["hands"], time.monotonic())
        node.publish("/hand/shape", {"shapes": shapes}, stamp_ns=msg.stamp_ns,
                     frame_id=msg.data["header"]["frame_id"])
    return node, on_keypoints


def main() -> None:
    spin(start)   # its own loop; in a container, the executor calls the handler instead


if __name__ == "__main__":
    run(main)
