"""/hand/pose -> the input of dex-retargeting (github.com/dexsuite/dex-retargeting), which stays
uninstalled here: numpy (+ pyzmq and msgpack for the live loop), no handmocap import.

dex-retargeting's examples retarget MediaPipe's world landmarks (SingleHandDetector.detect):
21 joints in MediaPipe's order (handmocap's order too: no reordering), metres, the wrist at
the origin, rotated into a wrist frame estimated from the wrist, index MCP and middle MCP and
then by a fixed per-hand matrix into what it calls the MANO convention:
    joint_pos = (p - p[0]) @ wrist_frame(p) @ OPERATOR2MANO[hand]           (21, 3) metres
Here p is /hand/pose `xyz` (metric, camera frame: only its shape matters, the rotation drops
out). In that frame, for either hand, the middle MCP lies on +z; the index MCP is on +y for a
right hand and on -y for a left one. Feed it as their examples do:

    retargeting = RetargetingConfig.load_from_file(config_path).build()     # dex_retargeting
    ref = ref_value(joint_pos, retargeting.optimizer.target_link_human_indices,
                    retargeting.optimizer.retargeting_type)
    qpos = retargeting.retarget(ref)

Pick the hand by `handedness` (the anatomical hand, as its hand_type means it: their
SingleHandDetector with selfie=False swaps MediaPipe's mirrored labels for the same reason).
/hand/keypoints' xyz_rel would do too, but it is scale-normalized (|joint 0 - joint 9| = 1), and
the retargeting configs' scaling_factor expects metres: multiply it by a hand size first.

    python examples/dex_retargeting_input.py [right|left] [ENDPOINT]   # prints joint_pos live
"""
import json
import os
import sys
import tempfile

import numpy as np

# dex-retargeting's fixed rotations from its estimated wrist frame to its MANO convention
# (example/vector_retargeting/single_hand_detector.py), applied on the right: p @ M.
OPERATOR2MANO = {
    "right": np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "left": np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
}
WRIST, INDEX_MCP, MIDDLE_MCP = 0, 5, 9


def wrist_frame(xyz):
    """(3,3) rotation whose columns are the wrist frame's axes in xyz's frame: x from the middle
    MCP towards the wrist, y the normal of the plane (wrist, index MCP, middle MCP), z = x × y,
    with the sign of y chosen so that z points from the middle MCP towards the index MCP.
    xyz: (21,3) joints, any rigid frame, any unit."""
    xyz = np.asarray(xyz, dtype=np.float64)
    wrist, index, middle = xyz[WRIST], xyz[INDEX_MCP], xyz[MIDDLE_MCP]
    normal = np.cross(index - wrist, middle - wrist)   # the 3 points' plane (their SVD fit, exactly)
    normal /= np.linalg.norm(normal)
    x = wrist - middle
    x -= (x @ normal) * normal                          # Gram-Schmidt: x in the palm plane
    x /= np.linalg.norm(x)
    z = np.cross(x, normal)
    if z @ (index - middle) < 0:                        # z towards the index side
        normal, z = -normal, -z
    return np.stack([x, normal, z], axis=1)


def retargeting_joint_pos(xyz, handedness):
    """(21,3) joints (metres, MediaPipe order, e.g. /hand/pose xyz) -> dex-retargeting's
    joint_pos (21,3): wrist-relative, in its MANO-convention wrist frame."""
    xyz = np.asarray(xyz, dtype=np.float64)
    rel = xyz - xyz[WRIST]
    return rel @ wrist_frame(xyz) @ OPERATOR2MANO[handedness]


def ref_value(joint_pos, indices, retargeting_type):
    """What retargeting.retarget() takes, as dex-retargeting's examples form it: the joints
    themselves for POSITION retargeting, else vectors joint_pos[task] - joint_pos[origin] with
    indices (2, K) = (origin row, task row)."""
    indices = np.asarray(indices)
    if str(retargeting_type).upper().endswith("POSITION"):
        return joint_pos[indices, :]
    return joint_pos[indices[1], :] - joint_pos[indices[0], :]


def main():
    hand_type = sys.argv[1] if len(sys.argv) > 1 else "right"
    import msgpack
    import zmq
    run_dir = os.environ.get("HANDMOCAP_RUN_DIR") or os.path.join(
        tempfile.gettempdir(), f"handmocap-{os.getuid()}", os.environ.get("HANDMOCAP_GRAPH", "default"))
    endpoint = sys.argv[2] if len(sys.argv) > 2 else json.load(open(os.path.join(run_dir, "ik.json")))["endpoint"]
    sock = zmq.Context().socket(zmq.SUB)
    sock.connect(endpoint)
    sock.subscribe(b"/hand/pose\0")
    while (frames := sock.recv_multipart())[1] != b"_eos":
        for hand in msgpack.unpackb(frames[2])["hands"]:
            if hand["handedness"] == hand_type:
                a = hand["xyz"]
                xyz = np.frombuffer(a["data"], a["dtype"]).reshape(a["shape"])
                print(np.round(retargeting_joint_pos(xyz, hand_type), 4).tolist(), flush=True)


if __name__ == "__main__":
    main()
