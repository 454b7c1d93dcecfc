"""Test node: publishes /hand/keypoints of one synthetic hand (bundled model, shape `beta`,
random poses within the joint limits), projected with a default K, plus /camera/info."""
import numpy as np

from handmocap.perception import camera_info
from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import JointLimits
from handmocap.runtime.node import Node, run
from handmocap.perception.skeleton import normalize_joints

PARAMS = {"frames": 60, "beta": [0.0] * 10, "seed": 0, "handedness": "right", "track_id": 1}


def synthetic_hands(frames, beta, seed, width=640, height=480):
    """(uv (F,21,2) px, xyz_rel (F,21,3), K (3,3)): the model's joints 0.5 m in front of a
    default camera, palm towards it, in random plausible poses."""
    model = HandModel.load()
    rng = np.random.default_rng(seed)
    beta = np.asarray(beta, dtype=np.float64)
    poses = JointLimits.for_model(model, beta).sample(frames, rng)
    _, joints = model.forward(poses, np.tile(beta, (frames, 1)))
    xyz = joints - joints[:, :1] + np.array([0.0, 0.0, 0.5])
    K = camera_info.default_K(width, height)
    uv = (xyz @ K.T)[..., :2] / xyz[..., 2:]
    return uv.astype(np.float32), normalize_joints(xyz).astype(np.float32), K


def main():
    node = Node("keypoints_source", params=PARAMS)
    p = node.params
    node.advertise("/hand/keypoints", "HandKeypoints")
    node.advertise("/camera/info", "CameraInfo")
    uv, xyz_rel, K = synthetic_hands(p["frames"], p["beta"], p["seed"])
    for i in range(p["frames"]):
        lo, hi = uv[i].min(0), uv[i].max(0)
        hand = {"track_id": p["track_id"], "handedness": p["handedness"], "score": 0.99,
                "bbox": np.concatenate([lo, hi]).astype(np.float32), "uv": uv[i],
                "confidence": np.ones(21, np.float32), "xyz_rel": xyz_rel[i]}
        node.publish("/camera/info", camera_info.camera_info_message(K, np.zeros(5), 640, 480, "default-fov"))
        node.publish("/hand/keypoints", {"width": 640, "height": 480, "hands": [hand]})
    node.close()


if __name__ == "__main__":
    run(main)
