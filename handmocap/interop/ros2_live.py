"""ROS 2, live, for the graph's `ros2` and `ros2_camera` nodes: rclpy and Fast DDS from PyPI
(pip install -e '.[ros2]'), no ROS install and no code of ours on the wire.

- Out: the messages of handmocap.interop.ros2_messages (rosbags' definitions) are serialized
  to CDR by rosbags and published as they are by rclpy publishers of the same ROS type
  (`Publisher.publish(bytes)`), the bytes `handbag export --ros2` writes into a bag. At start
  each type's rclpy definition is checked field by field against rosbags' (`same_fields`).
  A type that rclpy can't import here (tf2_msgs: not on PyPI) is left out with one log line;
  with a ROS install sourced it is published too.
- In: a ROS 2 `sensor_msgs/Image` or `CompressedImage` and its `CameraInfo` as the project's
  Image and CameraInfo bodies (`image_body`, `info_body`).

Safe by default: `rclpy_node` limits DDS discovery to this host (ROS_AUTOMATIC_DISCOVERY_RANGE
LOCALHOST) and binds Fast DDS's receiving sockets to the loopback interface (LOOPBACK_PROFILE)
unless the node's `discovery` param says "subnet" (the ZeroMQ side's CURVE rule,
docs/reference.md "Security"). ROS_DOMAIN_ID is rclpy's own (the environment's).

QoS (`qos`): images and camera info published as ROS 2 camera drivers send them (sensor data:
best effort, last 5) and taken "best available" (reliable from a reliable driver); hands,
robots and markers reliable (last RELIABLE_DEPTH), as joint states are.
"""
from __future__ import annotations

import atexit
import contextlib
import importlib
import os
import tempfile

import cv2
import numpy as np

from handmocap.perception.camera_info import camera_info_message

DISCOVERY = {"localhost": "LOCALHOST", "subnet": "SUBNET", "off": "OFF"}
SENSOR_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo")
# messages a reliable publisher keeps for a reader that lags (about 3 s of hands at 30 fps):
# with the ROS default of 10 a subscriber busy for a third of a second lost hands (KEEP_LAST
# replaces what was not yet acknowledged)
RELIABLE_DEPTH = 100
MISSING_HINT = "pip install -e '.[ros2]' (rclpy, Fast DDS and the message packages from PyPI)"


def check_discovery(node: str, value) -> None:
    if value not in DISCOVERY:
        raise ValueError(f"{node} param discovery: one of {', '.join(DISCOVERY)}, got {value!r}")


# Fast DDS participant profile for discovery "localhost": its receiving UDP sockets on the
# loopback interface only (and shared memory). ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST alone
# keeps discovery on this host but still binds them to 0.0.0.0 (`ss -lunp` while a node runs).
LOOPBACK_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>loopback_udp</transport_id>
        <type>UDPv4</type>
        <interfaceWhiteList><address>127.0.0.1</address></interfaceWhiteList>
      </transport_descriptor>
      <transport_descriptor>
        <transport_id>shm</transport_id>
        <type>SHM</type>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="handmocap_localhost" is_default_profile="true">
      <rtps>
        <userTransports>
          <transport_id>loopback_udp</transport_id>
          <transport_id>shm</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def set_discovery(discovery: str) -> None:
    """The environment Fast DDS reads at rclpy.init for `discovery` (DISCOVERY): the range, and
    for "localhost" LOOPBACK_PROFILE, unless FASTDDS_DEFAULT_PROFILES_FILE names one already
    (the user's own profile wins)."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = DISCOVERY[discovery]
    if discovery == "localhost" and not os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE"):
        fd, path = tempfile.mkstemp(prefix="handmocap_fastdds_", suffix=".xml")     # ours alone (0600)
        with os.fdopen(fd, "w") as f:
            f.write(LOOPBACK_PROFILE)
        atexit.register(os.unlink, path)
        os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = path


@contextlib.contextmanager
def rclpy_node(name: str, discovery: str = "localhost"):
    """`with rclpy_node(name, discovery) as (node, executor):` an rclpy node in its own context
    (safe in a container's thread: rclpy installs no signal handler; the graph's node stops on
    its own), DDS discovery as `discovery` asks; shut down on leaving."""
    check_discovery(name, discovery)
    set_discovery(discovery)
    try:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
    except ImportError as e:
        raise RuntimeError(f"{name}: ROS 2's rclpy is not installed ({e}): {MISSING_HINT}") from None
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        if context.ok():
            context.shutdown()


def qos(msgtype: str, reliable: bool | None = None):
    """The QoS profile for `msgtype` (module docstring); reliable=True/False overrides."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    if reliable is None:
        reliable = msgtype not in SENSOR_TYPES
    if not reliable:
        return qos_profile_sensor_data
    return QoSProfile(depth=RELIABLE_DEPTH, reliability=ReliabilityPolicy.RELIABLE)


def publishers_qos(node, topic: str, msgtype: str):
    """The QoS to take `topic` with, as its publishers send it: reliable when every publisher
    found is reliable, else best effort (sensor data); None while none is found. Decided once
    a publisher is known (rclpy's BEST_AVAILABLE decides when the subscription is made, and a
    camera driver started after it would get none). Best effort took only 54 of 160 raw
    352x640 frames of a reliable publisher here (Fast DDS fragments large frames: one lost
    fragment is a lost frame); reliable took 160 of 160."""
    from rclpy.qos import ReliabilityPolicy
    found = node.get_publishers_info_by_topic(topic)
    if not found:
        return None
    return qos(msgtype, all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in found))


def ros_class(msgtype: str):
    """rclpy's class of "pkg/msg/Name", or None when its package is not installed."""
    package, _, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None


def same_fields(cls, typestore, msgtype: str) -> bool:
    """rclpy's definition of `msgtype` (`cls`) has rosbags' fields, in order, nested types
    included: CDR bytes from one then read as the other."""
    ours = list(typestore.fielddefs[msgtype][1])
    theirs = list(cls.get_fields_and_field_types().items())
    if [n for n, _ in ours] != [n for n, _ in theirs]:
        return False
    for (field, (kind, spec)), (_, ros_type) in zip(ours, theirs):
        nested = spec if isinstance(spec, str) else spec[0][1] if isinstance(spec[0], tuple) else None
        if isinstance(nested, str) and "/" in nested:
            nested_cls = ros_class(nested)
            if nested_cls is None or not same_fields(nested_cls, typestore, nested):
                return False
    return True


class RawPublishers:
    """rclpy publishers, one per ROS topic, created on first use, publishing rosbags messages
    as their CDR bytes; a type rclpy lacks is left out (logged once)."""

    def __init__(self, node, typestore, prefix: str, log):
        self.node, self.ts, self.log = node, typestore, log
        self.prefix = "/" + prefix.strip("/") if prefix.strip("/") else ""
        self.publishers: dict[str, object] = {}
        self.left_out: set[str] = set()
        self.sent = 0

    def topic(self, topic: str) -> str:
        return self.prefix + topic

    def advertise(self, topics: dict[str, str]) -> None:
        """Create the publishers of {topic: ROS type} now: DDS matches them with subscribers
        while the graph starts, so the first hands are not published to nobody."""
        for topic, msgtype in topics.items():
            self._publisher(topic, msgtype)

    def _publisher(self, topic: str, msgtype: str):
        pub = self.publishers.get(topic)
        if pub is None and topic not in self.left_out:
            cls = ros_class(msgtype)
            if cls is None or not same_fields(cls, self.ts, msgtype):
                self.left_out.add(topic)
                why = "not installed" if cls is None else "a different definition from rosbags'"
                self.log.warning("ros2: %s not published: %s is %s here (%s)", self.topic(topic), msgtype, why,
                                 "tf2_msgs is not on PyPI; a sourced ROS install has it" if
                                 msgtype.startswith("tf2_msgs") else MISSING_HINT)
                return None
            pub = self.publishers[topic] = self.node.create_publisher(
                cls, self.topic(topic), qos(msgtype, reliable=msgtype not in SENSOR_TYPES))
        return pub

    def publish(self, topic: str, msgtype: str, message) -> bool:
        pub = self._publisher(topic, msgtype)
        if pub is None:
            return False
        pub.publish(bytes(self.ts.serialize_cdr(message, msgtype)))
        self.sent += 1
        return True


# ------------------------------------------------------------------ ROS 2 camera in
RAW_ENCODINGS = {"bgr8": 3, "rgb8": 3, "mono8": 1, "bgra8": 4, "rgba8": 4}


def stamp_ns(header) -> int:
    """A ROS header's stamp in ns."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def image_body(msg) -> dict:
    """A ROS 2 sensor_msgs Image or CompressedImage (rclpy's object) -> the project's Image body
    (no header): bgr8, rgb8 and mono8 as they are (rows cut to their width), bgra8/rgba8 and
    compressed frames (JPEG, PNG) as bgr8. ValueError naming the encoding for anything else."""
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, (bytes, memoryview)) else msg.data, np.uint8)
    if hasattr(msg, "format"):                                      # CompressedImage
        frame = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if frame is None:
            raise ValueError(f"a CompressedImage of format {msg.format!r} that OpenCV can't decode")
        return {"encoding": "bgr8", "width": frame.shape[1], "height": frame.shape[0], "data": frame}
    channels = RAW_ENCODINGS.get(msg.encoding)
    if channels is None:
        raise ValueError(f"an Image of encoding {msg.encoding!r} (taken: {', '.join(RAW_ENCODINGS)}, or a "
                         f"CompressedImage topic)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if data.size < h * step or step < w * channels:
        raise ValueError(f"an Image of {data.size} bytes for {w}x{h} {msg.encoding} with step {step}")
    pixels = data[:h * step].reshape(h, step)[:, :w * channels]
    frame = pixels.reshape(h, w, channels) if channels > 1 else pixels.reshape(h, w)
    if channels == 4:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR if msg.encoding == "bgra8" else cv2.COLOR_RGBA2BGR)
    encoding = "bgr8" if channels == 4 else msg.encoding
    return {"encoding": encoding, "width": w, "height": h, "data": np.ascontiguousarray(frame)}


def info_body(msg) -> dict:
    """A ROS 2 sensor_msgs CameraInfo (rclpy's object) -> the project's CameraInfo body: K from
    `k`, OpenCV distortion from `d` (plumb_bob and rational_polynomial are OpenCV's order)."""
    K = np.asarray(msg.k, np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"a CameraInfo without a camera matrix (k = {list(np.asarray(msg.k))})")
    return camera_info_message(K, np.asarray(msg.d, np.float64), msg.width, msg.height, "ros2")
