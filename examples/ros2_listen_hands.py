"""Print the hands the graph's `ros2` node publishes, as any ROS 2 program gets them: plain
rclpy, no handmocap import (pip install -e '.[ros2]', or a ROS 2 install).
    python examples/ros2_listen_hands.py                  # hand_right/left joint states, keypoints, markers
    python examples/ros2_listen_hands.py --prefix robot1  # the ros2 node's prefix:=robot1
    python examples/ros2_listen_hands.py --jsonl hands.jsonl --seconds 20   # every message's values, a line each
Discovery stays on this host unless ROS_AUTOMATIC_DISCOVERY_RANGE says otherwise (the ros2
node's default too); ROS_DOMAIN_ID as for any ROS 2 process.
"""
import argparse
import json
import os
import sys
import time

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
import rclpy                                                           # noqa: E402
from geometry_msgs.msg import PoseArray, PoseStamped                   # noqa: E402
from rclpy.executors import ExternalShutdownException                  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy                    # noqa: E402
from sensor_msgs.msg import JointState                                 # noqa: E402
from visualization_msgs.msg import MarkerArray                         # noqa: E402


def stamp_ns(header):
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def values(msg):
    """The values of one message as plain JSON."""
    if isinstance(msg, JointState):
        return {"name": list(msg.name), "position": list(msg.position)}
    if isinstance(msg, PoseArray):
        return {"xyz": [[p.position.x, p.position.y, p.position.z] for p in msg.poses],
                "xyzw": [[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w] for p in msg.poses]}
    if isinstance(msg, PoseStamped):
        p = msg.pose
        return {"xyz": [p.position.x, p.position.y, p.position.z],
                "xyzw": [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]}
    return {"markers": {m.ns: [[q.x, q.y, q.z] for q in m.points] for m in msg.markers},
            "frame_id": msg.markers[0].header.frame_id if msg.markers else ""}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--prefix", default="")
    p.add_argument("--jsonl", help="write every message's values here, one JSON line each (no printing)")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: Ctrl-C)")
    args = p.parse_args()
    prefix = "/" + args.prefix.strip("/") if args.prefix.strip("/") else ""
    rclpy.init()
    node = rclpy.create_node("hand_listener")
    out = open(args.jsonl, "w") if args.jsonl else None
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)

    def on_message(topic):
        def callback(msg):
            header = msg.markers[0].header if isinstance(msg, MarkerArray) and msg.markers else getattr(msg, "header", None)
            stamp = stamp_ns(header) if header is not None else 0
            if out:
                out.write(json.dumps({"topic": topic, "stamp_ns": stamp, "received_ns": time.time_ns(),
                                      **values(msg)}) + "\n")
                out.flush()
            elif isinstance(msg, JointState):
                flex = dict(zip(msg.name, msg.position))
                print(topic, stamp, "index PIP flexion %.2f rad" % flex.get(f"{topic.split('/')[-2]}/index_pip_flexion", 0),
                      flush=True)
        return callback

    subscriptions = {}
    for side in ("right", "left"):
        for suffix, kind in (("joint_states", JointState), ("keypoints", PoseArray), ("wrist_pose", PoseStamped)):
            topic = f"{prefix}/hand_{side}/{suffix}"
            subscriptions[topic] = node.create_subscription(kind, topic, on_message(topic), reliable)
    topic = f"{prefix}/hand_markers"
    subscriptions[topic] = node.create_subscription(MarkerArray, topic, on_message(topic), reliable)
    print("listening", flush=True, file=sys.stderr)
    end = time.monotonic() + args.seconds if args.seconds else None
    try:
        while rclpy.ok() and (end is None or time.monotonic() < end):
            rclpy.spin_once(node, timeout_sec=0.1)
            for topic in [t for t, sub in subscriptions.items() if sub.get_publisher_count()]:
                # DDS discovery: a publisher is found between ~0.1 and ~2 s after it starts
                print("matched", topic, flush=True, file=sys.stderr)
                del subscriptions[topic]
    except (KeyboardInterrupt, ExternalShutdownException):          # Ctrl-C, or SIGTERM through rclpy
        pass
    finally:
        if out:
            out.close()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
