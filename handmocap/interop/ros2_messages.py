"""The project's messages as ROS 2 messages: one conversion, used by `handbag export --ros2`
(written into a rosbag2) and by the live `ros2` node (published with rclpy). The ROS 2 types
and their CDR serialization are rosbags' (pip install -e '.[ros2]'): no encoder of ours.

Conventions (REP-103/105): metres, quaternions (x, y, z, w), stamps from the capture time of
the frame (the project's header stamp), the camera's frame an optical frame
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
                    -> /hand_markers             visualization_msgs/MarkerArray: per side the bones
                                                 (LINE_LIST, ns hand_<side>/bones) and joints
                                                 (SPHERE_LIST, ns hand_<side>/joints), camera frame,
                                                 a MARKER_LIFETIME_S lifetime (a lost hand fades)
    RobotJointStates -> /robot_<side>/joint_states sensor_msgs/JointState (the robot's names)
Other types have no counterpart here. A joint frame's orientation is the model's rest axes
turned by the bone that ends at the joint (the wrist: the whole hand's); a left hand's is the
mirror image of the right-hand model's (a proper rotation, rotations.mirror_quat).
"""
from __future__ import annotations

import numpy as np

from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import JointLimits
from handmocap.perception.pose import surest_per_side
from handmocap.perception.rotations import mirror_quat, quat_conjugate, quat_multiply, quat_rotate
from handmocap.perception.skeleton import BONES, JOINT_NAMES, NON_TIP_JOINTS, PARENTS
from handmocap.runtime.frames import compressed

SIDES = ("right", "left")
FINGER_JOINT_NAMES = [JOINT_NAMES[j] for j in NON_TIP_JOINTS[1:]]           # the 15 of JointLimits
ANGLE_NAMES = ("flexion", "abduction", "twist")
JPEG_QUALITY = 90
MARKER_LIFETIME_S = 0.25        # RViz drops a hand's markers this long after its last pose
MARKER_RGBA = {"right": (1.0, 0.55, 0.1, 1.0), "left": (0.2, 0.6, 1.0, 1.0)}
BONE_WIDTH_M, JOINT_DIAMETER_M = 0.004, 0.008
OPTICAL = "_optical_frame"


# {ROS topic: ROS type} of every topic Ros2Messages.convert gives (the table above)
TOPICS = {"/camera/image/compressed": "sensor_msgs/msg/CompressedImage",
          "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
          **{f"/hand_{side}/{suffix}": msgtype for side in SIDES for suffix, msgtype in (
              ("wrist_pose", "geometry_msgs/msg/PoseStamped"), ("keypoints", "geometry_msgs/msg/PoseArray"),
              ("joint_states", "sensor_msgs/msg/JointState"))},
          "/tf": "tf2_msgs/msg/TFMessage",
          "/hand_markers": "visualization_msgs/msg/MarkerArray",
          **{f"/robot_{side}/joint_states": "sensor_msgs/msg/JointState" for side in SIDES}}


def optical_frame(frame_id: str) -> str:
    """The optical frame of camera `frame_id` (a frame id that already is one stays as it is:
    a ROS 2 camera's frames come back under their own name)."""
    return frame_id if frame_id.endswith(OPTICAL) else f"{frame_id}{OPTICAL}"


def hand_frame(side: str, joint: int) -> str:
    return f"hand_{side}/{JOINT_NAMES[joint]}"


def typestore():
    """rosbags' ROS 2 type store (the message definitions and their CDR serialization)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise RuntimeError("ROS 2 messages need rosbags: pip install -e '.[ros2]'") from None
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
        parent = np.maximum(PARENTS, 0)
        inv = quat_conjugate(q[parent])                                         # (21,4); row 0 unused
        t = np.where(PARENTS[:, None] < 0, xyz, quat_rotate(inv, xyz - xyz[parent]))       # (21,3)
        r = np.where(PARENTS[:, None] < 0, q, quat_multiply(inv, q))                       # (21,4)
        out = []
        for j in range(len(JOINT_NAMES)):
            parent_frame = camera_frame if PARENTS[j] < 0 else hand_frame(side, PARENTS[j])
            tf = self.T("geometry_msgs/msg/Transform", translation=self.vector(t[j]), rotation=self.quaternion(r[j]))
            out.append(self.T("geometry_msgs/msg/TransformStamped", header=self.header(stamp_ns, parent_frame),
                              child_frame_id=hand_frame(side, j), transform=tf))
        return out

    def hand_messages(self, hand, stamp_ns, camera_frame):
        """{topic suffix: message} of one hand: joint_states (first: what a robot waits for),
        keypoints, wrist_pose."""
        side, xyz, q = hand["handedness"], np.asarray(hand["xyz"], np.float64), self.joint_quats(hand)
        header = self.header(stamp_ns, camera_frame)
        angles = self.limits.angles(np.asarray(hand["pose"], np.float64))                    # (15,3) rad
        names = [f"hand_{side}/{joint}_{angle}" for joint in FINGER_JOINT_NAMES for angle in ANGLE_NAMES]
        return {
            "joint_states": self.T("sensor_msgs/msg/JointState", header=header, name=names,
                                   position=angles.reshape(-1).astype(np.float64),
                                   velocity=np.zeros(0), effort=np.zeros(0)),
            "keypoints": self.T("geometry_msgs/msg/PoseArray", header=header,
                                poses=[self.pose(p, r) for p, r in zip(xyz, q)]),
            "wrist_pose": self.T("geometry_msgs/msg/PoseStamped", header=header, pose=self.pose(xyz[0], q[0])),
        }

    def robot_joint_state(self, robot, stamp_ns, frame_id):
        return self.T("sensor_msgs/msg/JointState", header=self.header(stamp_ns, frame_id), name=list(robot["name"]),
                      position=np.asarray(robot["position"], np.float64), velocity=np.zeros(0), effort=np.zeros(0))

    def markers(self, hands: dict, stamp_ns: int, camera_frame: str):
        """MarkerArray of {side: hand}: bones (LINE_LIST) and joints (SPHERE_LIST) per side."""
        header = self.header(stamp_ns, camera_frame)
        lifetime = self.T("builtin_interfaces/msg/Duration", sec=int(MARKER_LIFETIME_S),
                          nanosec=int(MARKER_LIFETIME_S % 1 * 1e9))
        identity = self.pose(np.zeros(3), (1.0, 0.0, 0.0, 0.0))
        out = []
        for side, hand in hands.items():
            xyz = np.asarray(hand["xyz"], np.float64)
            color = self.T("std_msgs/msg/ColorRGBA", **dict(zip("rgba", MARKER_RGBA[side])))
            for k, (kind, shape, points, size) in enumerate((
                    ("bones", 5, [xyz[j] for bone in BONES for j in bone], BONE_WIDTH_M),       # LINE_LIST
                    ("joints", 7, list(xyz), JOINT_DIAMETER_M))):                                # SPHERE_LIST
                out.append(self.T(
                    "visualization_msgs/msg/Marker", header=header, ns=f"hand_{side}/{kind}", id=k,
                    type=shape, action=0, pose=identity,                                        # ADD
                    scale=self.vector((size, size, size)), color=color, lifetime=lifetime, frame_locked=False,
                    points=[self.point(p) for p in points], colors=[], texture_resource="",
                    texture=self.T("sensor_msgs/msg/CompressedImage", header=self.header(0, ""), format="",
                                   data=np.zeros(0, np.uint8)),
                    uv_coordinates=[], text="", mesh_resource="",
                    mesh_file=self.T("visualization_msgs/msg/MeshFile", filename="", data=np.zeros(0, np.uint8)),
                    mesh_use_embedded_materials=False))
        return self.T("visualization_msgs/msg/MarkerArray", markers=out)

    def convert(self, type_name: str, msg: dict, tf: bool = True) -> list[tuple[str, str, object]] | None:
        """One decoded project message -> [(ROS topic, ROS type, message)] (the module's table;
        [] for a pose without a hand; tf=False: no /tf); None for a type with no ROS 2 counterpart."""
        stamp, frame = msg["header"]["stamp_ns"], msg["header"]["frame_id"]
        if type_name == "Image":
            return [("/camera/image/compressed", "sensor_msgs/msg/CompressedImage", self.compressed_image(msg))]
        if type_name == "CameraInfo":
            return [("/camera/camera_info", "sensor_msgs/msg/CameraInfo", self.camera_info(msg))]
        if type_name == "RobotJointStates":
            return [(f"/robot_{robot['handedness']}/joint_states", "sensor_msgs/msg/JointState",
                     self.robot_joint_state(robot, stamp, frame)) for robot in msg["robots"]]
        if type_name != "HandPose":
            return None
        camera = optical_frame(frame)
        hands = {side: hand for side, hand in surest_per_side(msg["hands"]).items() if side in SIDES}
        out, transforms = [], []
        for side, hand in hands.items():
            out += [(f"/hand_{side}/{suffix}", m.__msgtype__, m)
                    for suffix, m in self.hand_messages(hand, stamp, camera).items()]
            if tf:
                transforms += self.transforms(hand, stamp, camera)
        if hands:
            if tf:
                out.append(("/tf", "tf2_msgs/msg/TFMessage", self.T("tf2_msgs/msg/TFMessage", transforms=transforms)))
            out.append(("/hand_markers", "visualization_msgs/msg/MarkerArray", self.markers(hands, stamp, camera)))
        return out
