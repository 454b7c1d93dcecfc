"""ik: joint rotations, MANO-style pose and camera-frame joints of every hand.
/hand/keypoints (+ /hand/shape, /camera/info) -> /hand/pose, and /hand/mesh while a
subscriber asks for it by name (the posed mesh costs ~0.4 ms a hand: not computed for
nobody, nor for catch-all subscribers such as the recorder).

A thin loop over handmocap.perception.pose.PoseEstimator (IKNet per hand, left hands mirrored into the
right-hand model, FK at the track's shape, Eq. 5 translation, One Euro smoothing per
track; its module docstring has the steps). /hand/shape gives each track's rest pose (the
paper's X_ref, D_ref); the bundled average hand until a shape is known. K from
/camera/info; a default field of view from the image size until one arrives.

Params: model (hand model path, default bundled), iknet ("int8", the default:
models/iknet_int8.onnx; "float32": models/iknet.onnx; or an ONNX path), threads (onnxruntime
intra-op threads), and every PoseEstimator setting: the fields of
handmocap.perception.pose.PoseSettings (xy_from_keypoints, hand_length, clamp_to_limits, smooth,
the filters' cut-offs, reset_after_s), each explained beside it.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from handmocap.perception import camera_info
from handmocap.perception.hand_model import HandModel
from handmocap.perception.ik_solver import IKSolver
from handmocap.runtime.node import Message, Node, check_file_param, check_number_param, run, spin
from handmocap.perception.pose import PoseEstimator, PoseSettings, mesh_message

SETTINGS = tuple(f.name for f in dataclasses.fields(PoseSettings))   # the params PoseSettings declares
PARAMS = {"model": None, "iknet": None, "threads": 1, **dataclasses.asdict(PoseSettings())}


def check_params(params: dict) -> None:
    """The launcher's check of a graph's ik params before any process starts: the model files
    exist, the switches are bools and the settings numbers (ValueError naming the param)."""
    check_file_param("ik", "model", params.get("model"))
    check_file_param("ik", "iknet", params.get("iknet"), ("int8", "float32"), "handtrain iknet")
    check_number_param("ik", "threads", params.get("threads", PARAMS["threads"]), minimum=1, integer=True)
    try:
        PoseSettings(**{k: params[k] for k in SETTINGS if k in params})
    except ValueError as e:
        raise ValueError(f"ik param {e}") from None


def start() -> tuple[Node, Callable[[Message], None]]:
    """The node, set up (topics, models), and its handler of one received message."""
    node = Node("ik", params=PARAMS)
    p = node.params
    # topics first, models second: subscribers of /hand/pose connect while the models load
    node.subscribe("/hand/keypoints", "HandKeypoints", mode="all")   # every frame's pose is recorded
    # in order with the keypoints where both come the same way (both from this container, or
    # both from other processes): then they share one socket
    node.subscribe("/camera/info", "CameraInfo", mode="all")
    node.subscribe("/hand/shape", "HandShape", mode="latest")
    node.advertise("/hand/pose", "HandPose")
    node.advertise("/hand/mesh", "HandMesh")
    model = HandModel.load(p["model"])
    solver = IKSolver.load(p["iknet"], threads=int(p["threads"]), model=model)
    try:   # onnxruntime sets up its buffers on a session's first run: not on the first frame
        solver.solve(solver.rest)
    except Exception as e:   # a file that loads but is not IKNet; onnxruntime's errors are no ValueError
        raise ValueError(f"IKNet model {p['iknet'] or 'models/iknet_int8.onnx'} does not take IKNet's input: "
                         f"{str(e).splitlines()[0][:200]}") from None
    estimator = PoseEstimator(solver, model, **{k: p[k] for k in SETTINGS})
    K = None
    mesh_joined = 0

    def on_message(msg: Message) -> None:
        nonlocal K, mesh_joined
        if msg.type == "CameraInfo":
            K = np.asarray(msg.data["K"], dtype=np.float64)
        elif msg.type == "HandShape":
            estimator.set_shapes(msg.data["shapes"])
        else:
            data = msg.data
            K_frame = K if K is not None else camera_info.default_K(data["width"], data["height"])
            hands = estimator.update(data["hands"], K_frame, msg.stamp_ns / 1e9)
            frame_id = data["header"]["frame_id"]
            node.publish("/hand/pose", {"hands": hands}, stamp_ns=msg.stamp_ns, frame_id=frame_id)
            wanted, joined = node.named_subscribers("/hand/mesh")
            if wanted:
                body = mesh_message(model, hands)
                if joined > mesh_joined:        # somebody new: the faces ride along once
                    body["faces"], mesh_joined = model.faces.astype(np.int32), joined
                node.publish("/hand/mesh", body, stamp_ns=msg.stamp_ns, frame_id=frame_id)
    return node, on_message


def main() -> None:
    spin(start)   # its own loop; in a container, the executor calls the handler instead


if __name__ == "__main__":
    run(main)
