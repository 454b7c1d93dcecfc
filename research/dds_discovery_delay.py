"""How long a ROS 2 subscriber already running takes to get a new publisher's messages on this
host (Fast DDS discovery, rclpy from PyPI): the figure behind "0.1-2 s" in docs/reference.md.

    python research/dds_discovery_delay.py [--trials 8]

Per trial, in its own ROS_DOMAIN_ID: examples/ros2_listen_hands.py listens; 1.5 s later a
publisher process sends JointState on /hand_right/joint_states at 30 Hz, numbered 0, 1, ...;
the first number the listener got x 33 ms is the delay. Discovery range LOCALHOST, default
transports (UDP and shared memory), as a user's own ROS 2 program has them.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PUBLISHER = r"""
import time, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
rclpy.init()
node = rclpy.create_node("numbered")
pub = node.create_publisher(JointState, "/hand_right/joint_states", QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
for i in range(120):
    msg = JointState(name=["i"], position=[float(i)])
    msg.header.stamp.sec = 1
    pub.publish(msg)
    time.sleep(1 / 30)
"""


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=8)
    args = p.parse_args()
    delays = []
    for trial in range(args.trials):
        env = {**os.environ, "ROS_DOMAIN_ID": str(60 + trial), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
        with tempfile.TemporaryDirectory() as d:
            out = Path(d) / "got.jsonl"
            listener = subprocess.Popen([sys.executable, str(ROOT / "examples" / "ros2_listen_hands.py"), "--jsonl",
                                         str(out), "--seconds", "8"], env=env, stderr=subprocess.DEVNULL)
            time.sleep(1.5)
            subprocess.run([sys.executable, "-c", PUBLISHER], env=env, check=True)
            listener.wait(timeout=30)
            got = [json.loads(line)["position"][0] for line in out.read_text().splitlines()]
        first = int(got[0]) if got else None
        delays.append(None if first is None else first / 30)
        print(f"trial {trial + 1}: first message received {first} of 120 ({len(got)} in all)", flush=True)
    seen = sorted(d for d in delays if d is not None)
    print(f"delay until the first message, s: {', '.join(f'{d:.2f}' for d in seen)}; none in {delays.count(None)}")


if __name__ == "__main__":
    main()
