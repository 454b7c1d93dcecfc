"""ros2_camera: a ROS 2 camera as the graph's source. A ROS 2 `sensor_msgs/Image` (or
`CompressedImage`) topic and its `CameraInfo` -> `/camera/image` + `/camera/info`, each frame
stamped with its ROS header stamp (`header.stamp_ns`), so latency and pairing downstream
are the camera driver's.

A thin loop over handmocap.interop.ros2_live (image_body, info_body): rclpy is spun in this
node's own loop, so every frame is handled in order in the thread that publishes it.
/camera/info is published just before each image with its stamp, as the `camera` node does;
until the first CameraInfo arrives K is the 60 degree default (logged once). A frame that
can't be read (an encoding this graph does not take, a short buffer) is dropped, counted
and logged once per cause.

Params:
- image_topic: the ROS 2 image topic (a name ending in /compressed is a CompressedImage one).
- info_topic: its CameraInfo topic (default: camera_info beside the image topic, as
  image_transport names it: /camera/image_raw -> /camera/camera_info).
- reliable: null (default) takes the frames as the driver sends them: reliably from a driver
  that publishes reliably (best effort lost two thirds of raw 352x640 frames here: Fast DDS
  fragments them), best effort from one that publishes best effort (ros2_live.publishers_qos;
  the subscriptions are made once the driver is found); true or false forces one.
- discovery: "localhost" (default), "subnet" or "off" (handmocap.interop.ros2_live).
- frame_id: the frame id to publish (default: the ROS header's).
- timeout_s: end the stream after this long without a frame once frames came (a bag played
  with `ros2 bag play`); null: run until stopped.
Needs the optional extra: pip install -e '.[ros2]'.
"""
from __future__ import annotations

import time
from collections import deque

from handmocap.interop import ros2_live
from handmocap.perception.camera_info import camera_info_message, default_intrinsics
from handmocap.runtime.node import Node, check_bool_param, check_number_param, run

PARAMS = {"image_topic": "/camera/image_raw", "info_topic": None, "reliable": None, "discovery": "localhost",
          "frame_id": None, "timeout_s": None}
SPIN_S = 0.05           # longest one rclpy wait blocks before the loop looks at stop and timeout


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param)."""
    for key in ("image_topic", "info_topic", "frame_id"):
        value = params.get(key, PARAMS[key])
        if not (value is None and key != "image_topic") and not (isinstance(value, str) and value.strip("/")):
            raise ValueError(f"ros2_camera param {key}: a ROS 2 name, got {value!r}")
    if params.get("reliable") is not None:
        check_bool_param("ros2_camera", "reliable", params["reliable"])
    ros2_live.check_discovery("ros2_camera", params.get("discovery", PARAMS["discovery"]))
    check_number_param("ros2_camera", "timeout_s", params.get("timeout_s"), positive=True, null=True)


def info_topic_for(image_topic: str) -> str:
    """image_transport's CameraInfo topic beside `image_topic` (its compressed suffix dropped)."""
    base = image_topic[:-len("/compressed")] if image_topic.endswith("/compressed") else image_topic
    return base.rsplit("/", 1)[0] + "/camera_info" if "/" in base.strip("/") else "camera_info"


def main() -> None:
    node = Node("ros2_camera", params=PARAMS)
    try:
        with ros2_live.rclpy_node("handmocap_camera", node.params["discovery"]) as (ros, executor):
            read_camera(node, ros, executor, node.params)
    finally:
        node.close()


def read_camera(node: Node, ros, executor, p: dict) -> None:
    """The node's loop: each ROS 2 frame, in order, as /camera/info + /camera/image, until
    stopped or `timeout_s` without a frame."""
    compressed = p["image_topic"].endswith("/compressed")
    image_type = "sensor_msgs/msg/" + ("CompressedImage" if compressed else "Image")
    info_topic = p["info_topic"] or info_topic_for(p["image_topic"])
    frames, info = deque(), {}
    classes = {t: ros2_live.ros_class(t) for t in (image_type, "sensor_msgs/msg/CameraInfo")}
    if None in classes.values():
        raise RuntimeError(f"ros2_camera: sensor_msgs is not installed: {ros2_live.MISSING_HINT}")
    # topic -> (type, callback): subscribed once a publisher is found, with its reliability
    pending = {p["image_topic"]: (image_type, lambda m: frames.append(m)),
               info_topic: ("sensor_msgs/msg/CameraInfo", lambda m: info.__setitem__("latest", m))}
    node.advertise("/camera/info", "CameraInfo")
    node.advertise("/camera/image", "Image")
    node.log.info("reading %s (%s) and %s from ROS 2", p["image_topic"], image_type, info_topic)
    warned = set()                      # the default-K causes already logged
    received, unreadable, last_frame = 0, 0, None
    while node.ok():
        for topic, (msgtype, callback) in list(pending.items()):
            profile = ros2_live.qos(msgtype, p["reliable"]) if p["reliable"] is not None else \
                ros2_live.publishers_qos(ros, topic, msgtype)
            if profile is not None:
                ros.create_subscription(classes[msgtype], topic, callback, profile)
                node.log.info("taking %s %s", topic, "reliably" if profile.reliability.name == "RELIABLE"
                              else "best effort")
                del pending[topic]
        executor.spin_once(timeout_sec=SPIN_S)
        while frames:
            ros_image = frames.popleft()
            received += 1
            last_frame = time.monotonic()
            stamp, frame_id = ros2_live.stamp_ns(ros_image.header), p["frame_id"] or ros_image.header.frame_id
            try:
                image = ros2_live.image_body(ros_image)
                camera = camera_info(info.get("latest"), image, warned, node)
            except ValueError as e:     # counted in the node status, logged once per cause
                unreadable += 1
                node.drop(p["image_topic"], str(e), str(e), what="a ROS 2 frame")
                continue
            node.publish("/camera/info", camera, stamp_ns=stamp, frame_id=frame_id or "camera")
            node.publish("/camera/image", image, stamp_ns=stamp, frame_id=frame_id or "camera")
        if p["timeout_s"] and last_frame is not None and time.monotonic() - last_frame > p["timeout_s"]:
            node.log.info("ros2_camera: no frame for %g s after %d: end of stream", p["timeout_s"], received)
            break
    if unreadable:
        node.log.warning("ros2_camera: %d of %d frames dropped", unreadable, received)


def camera_info(ros_info, image: dict, warned: set, node: Node) -> dict:
    """The CameraInfo body for `image`: the ROS CameraInfo's when it matches the frame's size,
    else the default field of view (logged once)."""
    if ros_info is not None and (ros_info.width, ros_info.height) == (image["width"], image["height"]):
        return ros2_live.info_body(ros_info)
    why = "no CameraInfo yet" if ros_info is None else \
        f"CameraInfo is {ros_info.width}x{ros_info.height}, frames {image['width']}x{image['height']}"
    if why not in warned:
        warned.add(why)
        node.log.warning("ros2_camera: %s: K from a 60 degree field of view until it comes", why)
    intr = default_intrinsics(image["width"], image["height"])
    return camera_info_message(intr.K, intr.distortion, image["width"], image["height"], intr.source)


if __name__ == "__main__":
    run(main)
