"""Test node: a live camera-and-hand stand-in at `hz` for `seconds` (0: until stopped).
Per frame: /camera/info, /camera/image (grey bgr8 640x480), /hand/keypoints and /hand/pose
of one hand of known pose (bundled model, random poses; `handedness`, `track_id`), palm-ish
towards a default camera, its root at `root` metres. The HandPose fields come from
handmocap.perception.pose.pose_fields, the ik node's own code, so they agree as the ik node's do."""
import time

import numpy as np

from handmocap.perception import camera_info
from handmocap.perception.hand_model import HandModel
from handmocap.runtime.node import Node, run
from handmocap.perception.pose import pose_fields
from handmocap.training.pose_data import PoseSampler
from handmocap.perception.rotations import mirror_points
from handmocap.perception.skeleton import normalize_joints

PARAMS = {"hz": 30.0, "seconds": 0.0, "seed": 0, "handedness": "right", "track_id": 1,
          "root": [0.02, -0.01, 0.5], "poses": 16}
W, H = 640, 480


def synthetic_pose_hands(n, seed, handedness, track_id, root, K, model):
    """n (HandKeypoints hand, HandPose hand) pairs of known random poses and shapes."""
    d = PoseSampler(model).sample(n, np.random.default_rng(seed))
    _, joints = model.forward(d["quats"], d["beta"])
    rel = joints - joints[:, 9:10]
    if handedness == "left":
        rel = mirror_points(rel)
    xyz = rel + np.asarray(root, dtype=np.float64)
    uv = ((xyz @ K.T)[..., :2] / xyz[..., 2:]).astype(np.float32)
    pairs = []
    for i in range(n):
        kp = {"track_id": track_id, "handedness": handedness, "score": 0.95,
              "bbox": np.concatenate([uv[i].min(0), uv[i].max(0)]).astype(np.float32), "uv": uv[i],
              "confidence": np.ones(21, np.float32), "xyz_rel": normalize_joints(xyz[i]).astype(np.float32)}
        pairs.append((kp, pose_fields(kp, d["quats"][i], d["beta"][i], K, model)))
    return pairs


def main():
    node = Node("pose_source", params=PARAMS)
    p = node.params
    for topic, type_name in (("/camera/info", "CameraInfo"), ("/camera/image", "Image"),
                             ("/hand/keypoints", "HandKeypoints"), ("/hand/pose", "HandPose")):
        node.advertise(topic, type_name)
    K = camera_info.default_K(W, H)
    pairs = synthetic_pose_hands(int(p["poses"]), p["seed"], p["handedness"], int(p["track_id"]), p["root"],
                                 K, HandModel.load())
    image = np.full((H, W, 3), 96, np.uint8)
    info = camera_info.camera_info_message(K, np.zeros(5), W, H, "default-fov")
    t0, i = time.monotonic(), 0
    while node.ok() and (not p["seconds"] or i < p["seconds"] * p["hz"]):
        time.sleep(max(0.0, t0 + i / p["hz"] - time.monotonic()))
        stamp = time.time_ns()
        kp, pose = pairs[i % len(pairs)]
        node.publish("/camera/info", info, stamp_ns=stamp)
        node.publish("/camera/image", {"encoding": "bgr8", "width": W, "height": H, "data": image}, stamp_ns=stamp)
        node.publish("/hand/keypoints", {"width": W, "height": H, "hands": [kp]}, stamp_ns=stamp)
        node.publish("/hand/pose", {"hands": [pose]}, stamp_ns=stamp)
        i += 1
    node.close()


if __name__ == "__main__":
    run(main)
