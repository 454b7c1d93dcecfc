"""ros2: the graph's hands, live, on ROS 2 (rclpy and Fast DDS from PyPI; no ROS install).
/hand/pose, /camera/image, /camera/info, /robot/joint_states -> the ROS 2 topics that
`handbag export --ros2` writes (handmocap.interop.ros2_messages has the table):
`<prefix>/hand_<side>/joint_states`, `keypoints`, `wrist_pose`, `<prefix>/hand_markers`
(RViz), `<prefix>/camera/image/compressed`, `<prefix>/camera/camera_info`,
`<prefix>/robot_<side>/joint_states`; `/tf` only where rclpy has tf2_msgs (not on PyPI).

A thin loop over handmocap.interop.ros2_live.RawPublishers: each message converted once, CDR
bytes published by rclpy. Hands keep every message (reliable QoS); the camera is latest-only
and its JPEG costs about 3 ms a frame (images: false leaves it out).

Params: prefix (a namespace before every topic, e.g. "left_arm"), discovery ("localhost":
DDS finds peers on this host only, the default; "subnet": the robot's network; "off"),
images (publish the camera too), wait_for_subscriber_s (hold the hands back at start until
something subscribes to hand_right/joint_states, at most this long: DDS discovery takes
0.1-2 s, so a consumer started first would miss the first hands; 0, the default: never
wait, as live). ROS_DOMAIN_ID comes from the environment, as in any ROS 2
process. Needs the optional extra: pip install -e '.[ros2]'.
"""
from __future__ import annotations

import os
import time

from handmocap.interop import ros2_live
from handmocap.runtime.node import Node, check_bool_param, check_number_param, run
from handmocap.interop.ros2_messages import TOPICS, Ros2Messages, typestore

PARAMS = {"prefix": "", "discovery": "localhost", "images": True, "wait_for_subscriber_s": 0.0}
WAIT_TOPIC = "/hand_right/joint_states"     # the topic whose subscriber wait_for_subscriber_s waits for


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param)."""
    ros2_live.check_discovery("ros2", params.get("discovery", PARAMS["discovery"]))
    check_bool_param("ros2", "images", params.get("images", PARAMS["images"]))
    check_number_param("ros2", "wait_for_subscriber_s", params.get("wait_for_subscriber_s", 0.0), minimum=0)
    if not isinstance(params.get("prefix", ""), str):
        raise ValueError(f"ros2 param prefix: a topic namespace string, got {params.get('prefix')!r}")


def main() -> None:
    node = Node("ros2", params=PARAMS)
    p = node.params
    try:
        with ros2_live.rclpy_node("handmocap", p["discovery"]) as (ros, _):
            publish_hands(node, ros, p)
    finally:
        node.close()


def publish_hands(node: Node, ros, p: dict) -> None:
    """The node's loop: every input converted and published on ROS 2 until the inputs end."""
    ts = typestore()
    publishers = ros2_live.RawPublishers(ros, ts, p["prefix"], node.log)
    build = Ros2Messages(ts)
    publishers.advertise({t: m for t, m in TOPICS.items() if p["images"] or not t.startswith("/camera/image")})
    node.subscribe("/hand/pose", "HandPose", mode="all")
    node.subscribe("/robot/joint_states", "RobotJointStates", mode="all")
    node.subscribe("/camera/info", "CameraInfo", mode="latest")
    if p["images"]:
        node.subscribe("/camera/image", "Image", mode="latest")
    node.log.info("publishing hands on ROS 2 (domain %s, discovery %s, prefix %r)",
                  os.environ.get("ROS_DOMAIN_ID", "0"), p["discovery"], p["prefix"])
    deadline = time.monotonic() + p["wait_for_subscriber_s"]
    while publishers.publishers[WAIT_TOPIC].get_subscription_count() == 0 and time.monotonic() < deadline \
            and node.ok():
        time.sleep(0.02)                # poses queue up on the bus meanwhile (keep-all)
    tf = "/tf" not in publishers.left_out        # no /tf to build where it can't be published
    cpu_ns, count = {}, {}              # this thread's CPU time per input type: the node's cost
    for msg in node:
        t0 = time.thread_time_ns()
        for topic, msgtype, message in build.convert(msg.type, msg.data, tf) or ():
            publishers.publish(topic, msgtype, message)
        cpu_ns[msg.type] = cpu_ns.get(msg.type, 0) + time.thread_time_ns() - t0
        count[msg.type] = count.get(msg.type, 0) + 1
    node.log.info("ros2: %d ROS 2 messages published; CPU %s", publishers.sent, ", ".join(
        f"{cpu_ns[k] / count[k] / 1e6:.2f} ms a {k} ({count[k]})" for k in sorted(count)) or "idle")


if __name__ == "__main__":
    run(main)
