"""/hand/pose -> a robot hand, live, with dex-retargeting (pip install -e '.[retarget]').

The retarget node does this inside a graph (launch/teleop.yaml); this is the same loop as a
plain subscriber, to copy into a robot program: every /hand/pose message, the hand of one side
turned into dex-retargeting's input (handmocap.perception.retarget.retargeting_joint_pos: its joint order,
wrist frame and metres) and retargeted onto a robot hand, whose joint names and positions are
printed.

    python examples/dex_retargeting_input.py [right|left] [CONFIG] [URDF_DIR] [ENDPOINT]

CONFIG: a dex-retargeting config (.yml, or a name it ships such as allegro_hand_right; default
the project's toy hand, examples/robot_hand/toy_hand_right.yml); URDF_DIR: the folder its
urdf_path is relative to; ENDPOINT: the ik node's (default: read from the running graph).
"""
import json
import os
import sys
import tempfile
from pathlib import Path

import msgpack
import numpy as np
import zmq

from handmocap.perception.retarget import RobotHand

TOY_HAND = Path(__file__).resolve().parent / "robot_hand" / "toy_hand_right.yml"


def main():
    hand_type = sys.argv[1] if len(sys.argv) > 1 else "right"
    robot = RobotHand(sys.argv[2] if len(sys.argv) > 2 else TOY_HAND, sys.argv[3] if len(sys.argv) > 3 else None)
    run_dir = os.environ.get("HANDMOCAP_RUN_DIR") or os.path.join(
        tempfile.gettempdir(), f"handmocap-{os.getuid()}", os.environ.get("HANDMOCAP_GRAPH", "default"))
    info = os.path.join(run_dir, "ik.json")
    if len(sys.argv) < 5 and not os.path.exists(info):
        sys.exit(f"no ik node runs in {run_dir}: start a graph (handlaunch launch/teleop.yaml) or give an endpoint")
    endpoint = sys.argv[4] if len(sys.argv) > 4 else json.load(open(info))["endpoint"]
    sock = zmq.Context().socket(zmq.SUB)
    sock.connect(endpoint)
    sock.subscribe(b"/hand/pose\0")
    while (frames := sock.recv_multipart())[1] != b"_eos":
        for hand in msgpack.unpackb(frames[2])["hands"]:
            if hand["handedness"] == hand_type:
                a = hand["xyz"]
                xyz = np.frombuffer(a["data"], a["dtype"]).reshape(a["shape"])
                qpos = robot.retarget(xyz, hand_type)
                print(" ".join(f"{n}={q:.3f}" for n, q in zip(robot.joint_names, qpos)), flush=True)


if __name__ == "__main__":
    main()
