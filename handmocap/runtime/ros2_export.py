"""`handbag export --ros2 OUT`: a project bag as a ROS 2 bag (rosbag2: MCAP storage, CDR,
metadata.yaml) that `ros2 bag info` and `ros2 bag play` take, without a ROS install.

The ROS 2 types and their CDR serialization are rosbags' (pip install -e '.[ros2]'); no
encoder here. Conventions (REP-103/105): metres, quaternions (x, y, z, w), stamps from the
capture time of the frame (the project's header stamp), the camera's frame an optical frame
(`<frame_id>_optical_frame`: x right, y down, z forward, as the project's camera frame is).

    Image           -> /camera/image/compressed  sensor_msgs/CompressedImage (JPEG)
    CameraInfo      -> /camera/camera_info       sensor_msgs/CameraInfo (plumb_bob, R = I, P = [K|0])
    HandPose, per side (hand_right, hand_left: fixed names; of two hands of a side the surer):
                    -> /tf                       tf2_msgs/TFMessage: camera -> hand_<side>/wrist ->
                                                 ... -> hand_<side>/index_tip (21 frames, a tree
                                                 along the skeleton)
                    -> /hand_<side>/wrist_pose   geometry_msgs/PoseStamped (camera frame)
                    -> /hand_<side>/keypoints    geometry_msgs/PoseArray: the 21 joints in
                                                 skeleton.JOINT_NAMES order (camera frame)
                    -> /hand_<side>/joint_states sensor_msgs/JointState: the 15 finger joints'
                                                 anatomical flexion, abduction and twist (rad;
                                                 joint_limits.JointLimits), e.g.
                                                 hand_right/index_pip_flexion
    RobotJointStates -> /robot_<side>/joint_states sensor_msgs/JointState (the robot's names)
Other topics are left out (listed by the export). A joint frame's orientation is the model's
rest axes turned by the bone that ends at the joint (the wrist: the whole hand's); a left hand's
is the mirror image of the right-hand model's (a proper rotation, rotations.mirror_quat).
"""
from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

import numpy as np

from handmocap.runtime import codec
from handmocap.runtime.bag import iter_messages
from handmocap.runtime.frames import compressed
from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import JointLimits
from handmocap.perception.pose import surest_per_side
from handmocap.perception.rotations import mirror_quat, quat_multiply, quat_conjugate, quat_rotate
from handmocap.perception.skeleton import JOINT_NAMES, NON_TIP_JOINTS, PARENTS

SIDES = ("right", "left")
FINGER_JOINT_NAMES = [JOINT_NAMES[j] for j in NON_TIP_JOINTS[1:]]           # the 15 of JointLimits
ANGLE_NAMES = ("flexion", "abduction", "twist")
JPEG_QUALITY = 90


def optical_frame(frame_id: str) -> str:
    return f"{frame_id}_optical_frame"


def hand_frame(side: str, joint: int) -> str:
    return f"hand_{side}/{JOINT_NAMES[joint]}"


def _typestore():
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise RuntimeError("handbag export --ros2 needs rosbags: pip install -e '.[ros2]'") from None
    return get_typestore(Stores.ROS2_JAZZY)


class Ros2Messages:
    """Builds rosbags message objects from the project's decoded messages."""

    def __init__(self, typestore):
        self.ts = typestore
        self.T = lambda msgtype, **fields: typestore.types[msgtype](**fields)
        self.limits = JointLimits.for_model(HandModel.load())

    def header(self, stamp_ns: int, frame_id: str):
        stamp = self.T("builtin_interfaces/msg/Time", sec=int(stamp_ns // 1_000_000_000),
                       nanosec=int(stamp_ns % 1_000_000_000))
        return self.T("std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)

    def vector(self, v):
        return self.T("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def point(self, v):
        return self.T("geometry_msgs/msg/Point", x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quaternion(self, q_wxyz):
        w, x, y, z = (float(c) for c in q_wxyz)
        return self.T("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)

    def pose(self, p, q):
        return self.T("geometry_msgs/msg/Pose", position=self.point(p), orientation=self.quaternion(q))

    def compressed_image(self, msg):
        jpeg = compressed(msg, JPEG_QUALITY)["data"]
        return self.T("sensor_msgs/msg/CompressedImage", header=self.header(msg["header"]["stamp_ns"],
                      optical_frame(msg["header"]["frame_id"])), format="jpeg",
                      data=np.ascontiguousarray(jpeg, dtype=np.uint8).reshape(-1))

    def camera_info(self, msg):
        K = np.asarray(msg["K"], np.float64)
        P = np.concatenate([K, np.zeros((3, 1))], axis=1)
        roi = self.T("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.T("sensor_msgs/msg/CameraInfo",
                      header=self.header(msg["header"]["stamp_ns"], optical_frame(msg["header"]["frame_id"])),
                      height=int(msg["height"]), width=int(msg["width"]), distortion_model="plumb_bob",
                      d=np.asarray(msg["distortion"], np.float64), k=K.reshape(-1), r=np.eye(3).reshape(-1),
                      p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi)

    @staticmethod
    def joint_quats(hand) -> np.ndarray:
        """(21,4) w,x,y,z orientation of each joint frame in the camera frame (see module doc)."""
        q = np.asarray(hand["quat"], np.float64)
        return mirror_quat(q) if hand["handedness"] == "left" else q

    def transforms(self, hand, stamp_ns, camera_frame):
        """TransformStamped (21): camera -> wrist, then each joint in its parent joint's frame."""
        side, xyz, q = hand["handedness"], np.asarray(hand["xyz"], np.float64), self.joint_quats(hand)
        out = []
        for j in range(len(JOINT_NAMES)):
            parent = PARENTS[j]
            if parent < 0:
                t, r, parent_frame = xyz[j], q[j], camera_frame
            else:
                inv = quat_conjugate(q[parent])
                t, r, parent_frame = quat_rotate(inv, xyz[j] - xyz[parent]), quat_multiply(inv, q[j]), \
                    hand_frame(side, parent)
            tf = self.T("geometry_msgs/msg/Transform", translation=self.vector(t), rotation=self.quaternion(r))
            out.append(self.T("geometry_msgs/msg/TransformStamped", header=self.header(stamp_ns, parent_frame),
                              child_frame_id=hand_frame(side, j), transform=tf))
        return out

    def hand_messages(self, hand, stamp_ns, camera_frame):
        """{topic suffix: message} of one hand: wrist_pose, keypoints, joint_states."""
        side, xyz, q = hand["handedness"], np.asarray(hand["xyz"], np.float64), self.joint_quats(hand)
        header = self.header(stamp_ns, camera_frame)
        angles = self.limits.angles(np.asarray(hand["pose"], np.float64))                    # (15,3) rad
        names = [f"hand_{side}/{joint}_{angle}" for joint in FINGER_JOINT_NAMES for angle in ANGLE_NAMES]
        return {
            "wrist_pose": self.T("geometry_msgs/msg/PoseStamped", header=header, pose=self.pose(xyz[0], q[0])),
            "keypoints": self.T("geometry_msgs/msg/PoseArray", header=header,
                                poses=[self.pose(p, r) for p, r in zip(xyz, q)]),
            "joint_states": self.T("sensor_msgs/msg/JointState", header=header, name=names,
                                   position=angles.reshape(-1).astype(np.float64),
                                   velocity=np.zeros(0), effort=np.zeros(0)),
        }

    def robot_joint_state(self, robot, stamp_ns, frame_id):
        return self.T("sensor_msgs/msg/JointState", header=self.header(stamp_ns, frame_id), name=list(robot["name"]),
                      position=np.asarray(robot["position"], np.float64), velocity=np.zeros(0), effort=np.zeros(0))


def export_ros2(src: Path, dst: Path, topics=None) -> dict:
    """Write the rosbag2 folder `dst` (must not exist) from the project bag `src`. Returns
    {"topics": {ros topic: (type, count)}, "skipped": {project topic: reason}}."""
    ts = _typestore()
    partial = dst.with_name(dst.name + ".partial")     # renamed to dst once complete
    shutil.rmtree(partial, ignore_errors=True)
    try:
        result = _write(ts, src, partial, topics)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    # rosbag2 names the storage file after its folder: rename both
    (partial / f"{partial.name}.mcap").rename(partial / f"{dst.name}.mcap")
    meta = partial / "metadata.yaml"
    meta.write_text(meta.read_text().replace(f"{partial.name}.mcap", f"{dst.name}.mcap"))
    partial.rename(dst)
    return result


def _write(ts, src: Path, dst: Path, topics) -> dict:
    from rosbags.rosbag2 import StoragePlugin, Writer
    build = Ros2Messages(ts)
    counts, skipped = Counter(), {}
    types: dict[str, str] = {}
    with Writer(dst, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}

        def write(topic, msgtype, message, log_ns):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                types[topic] = msgtype
            writer.write(connections[topic], int(log_ns), ts.serialize_cdr(message, msgtype))
            counts[topic] += 1

        for topic, type_name, payload, log_ns in iter_messages(src, topics):
            try:
                msg = codec.decode(payload, type_name)
            except codec.MalformedMessage as e:
                skipped[topic] = f"malformed: {e}"
                continue
            stamp, frame = msg["header"]["stamp_ns"], msg["header"]["frame_id"]
            if type_name == "Image":
                write("/camera/image/compressed", "sensor_msgs/msg/CompressedImage", build.compressed_image(msg), log_ns)
            elif type_name == "CameraInfo":
                write("/camera/camera_info", "sensor_msgs/msg/CameraInfo", build.camera_info(msg), log_ns)
            elif type_name == "HandPose":
                camera = optical_frame(frame)
                hands = surest_per_side(msg["hands"])
                transforms = []
                for side in SIDES:
                    if side in hands:
                        transforms += build.transforms(hands[side], stamp, camera)
                        for suffix, m in build.hand_messages(hands[side], stamp, camera).items():
                            write(f"/hand_{side}/{suffix}", m.__msgtype__, m, log_ns)
                if transforms:
                    write("/tf", "tf2_msgs/msg/TFMessage", ts.types["tf2_msgs/msg/TFMessage"](transforms=transforms),
                          log_ns)
            elif type_name == "RobotJointStates":
                for robot in msg["robots"]:
                    write(f"/robot_{robot['handedness']}/joint_states", "sensor_msgs/msg/JointState",
                          build.robot_joint_state(robot, stamp, frame), log_ns)
            else:
                skipped.setdefault(topic, f"{type_name} has no ROS 2 counterpart here")
    return {"topics": {t: (types[t], n) for t, n in counts.items()}, "skipped": skipped}
