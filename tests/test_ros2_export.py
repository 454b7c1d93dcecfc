"""handbag export --ros2: a project bag as a rosbag2 (MCAP, CDR), read back by two readers
this project did not write (rosbags' and mcap-ros2-support's), every value checked against
the source bag."""
import importlib.util

import cv2
import numpy as np
import pytest
import yaml

from graphnodes.pose_source import synthetic_pose_hands
from handmocap.runtime import bag, codec
from handmocap.perception import camera_info
from handmocap.interop.bag_cli import main as handbag
from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import JointLimits
from handmocap.perception.rotations import mirror_points, quat_rotate
from handmocap.perception.skeleton import JOINT_NAMES, PARENTS

pytestmark = pytest.mark.skipif(importlib.util.find_spec("rosbags") is None,
                                reason="rosbags not installed (pip install -e '.[ros2]')")
MODEL = HandModel.load()
W, H = 64, 48
K = camera_info.default_K(W, H)
T0 = 1_700_000_000_000_000_000
N = 6


def source_bag(path):
    """N frames: image, camera info, keypoints (not exported), a pose with a right and a left
    hand (and a second, less sure right hand), robot joint states; returns the messages by type."""
    right = synthetic_pose_hands(N, 1, "right", 1, [0.02, 0.0, 0.5], K, MODEL)
    left = synthetic_pose_hands(N, 2, "left", 2, [-0.1, 0.0, 0.6], K, MODEL)
    extra = synthetic_pose_hands(N, 3, "right", 3, [0.1, 0.0, 0.7], K, MODEL)
    sent = {"Image": [], "CameraInfo": [], "HandPose": [], "RobotJointStates": []}
    with bag.BagWriter(path) as w:
        for i in range(N):
            stamp = T0 + i * 33_333_333
            h = codec.header(i, stamp_ns=stamp)
            frame = np.full((H, W, 3), 60, np.uint8)
            cv2.circle(frame, (10 + 5 * i, 24), 8, (0, 0, 255), -1)
            weaker = {**extra[i][1], "score": 0.5, "confidence": extra[i][1]["confidence"] * 0.5}
            msgs = {
                "Image": {"header": h, "encoding": "bgr8", "width": W, "height": H, "data": frame},
                "CameraInfo": {"header": h, "width": W, "height": H, "K": K, "distortion": np.zeros(5)},
                "HandKeypoints": {"header": h, "width": W, "height": H, "hands": [right[i][0]]},
                "HandPose": {"header": h, "hands": [weaker, right[i][1], left[i][1]]},
                "RobotJointStates": {"header": h, "robots": [{"handedness": "right", "track_id": 1, "robot": "toy",
                                                              "name": ["a", "b"], "position": np.array([0.1 * i, -0.2])}]},
            }
            topics = {"Image": "/camera/image", "CameraInfo": "/camera/info", "HandKeypoints": "/hand/keypoints",
                      "HandPose": "/hand/pose", "RobotJointStates": "/robot/joint_states"}
            for k, (kind, body) in enumerate(msgs.items()):
                w.write(topics[kind], kind, codec.encode(body, kind), stamp + 1000 + k, stamp)
                if kind in sent:
                    sent[kind].append(body)
    return sent


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("ros2")
    sent = source_bag(d / "src.mcap")
    assert handbag(["export", str(d / "src.mcap"), "--ros2", str(d / "out")]) == 0
    return sent, d / "out"


def rosbags_messages(folder):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    out = {}
    with Reader(folder) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((conn.msgtype, t, ts.deserialize_cdr(raw, conn.msgtype)))
    return out


def xyzw(q_wxyz):
    return np.array([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]])


def test_metadata_lists_every_topic_with_type_and_count(exported):
    _, folder = exported
    meta = yaml.safe_load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["storage_identifier"] == "mcap" and meta["relative_file_paths"] == ["out.mcap"]
    listed = {t["topic_metadata"]["name"]: (t["topic_metadata"]["type"], t["message_count"])
              for t in meta["topics_with_message_count"]}
    per_side = {f"/hand_{s}/{k}": (m, N) for s in ("right", "left") for k, m in (
        ("wrist_pose", "geometry_msgs/msg/PoseStamped"), ("keypoints", "geometry_msgs/msg/PoseArray"),
        ("joint_states", "sensor_msgs/msg/JointState"))}
    assert listed == {"/camera/image/compressed": ("sensor_msgs/msg/CompressedImage", N),
                      "/camera/camera_info": ("sensor_msgs/msg/CameraInfo", N),
                      "/tf": ("tf2_msgs/msg/TFMessage", N),
                      "/hand_markers": ("visualization_msgs/msg/MarkerArray", N),
                      "/robot_right/joint_states": ("sensor_msgs/msg/JointState", N), **per_side}
    assert meta["message_count"] == sum(n for _, n in listed.values())
    assert [p.name for p in folder.iterdir()] and not (folder.parent / "out.partial").exists()


def test_every_message_reads_back_with_rosbags_and_matches_the_source(exported):
    sent, folder = exported
    got = rosbags_messages(folder)
    limits = JointLimits.for_model(MODEL)
    for i in range(N):
        stamp = T0 + i * 33_333_333
        img = got["/camera/image/compressed"][i][2]
        assert img.format == "jpeg" and img.header.frame_id == "camera_optical_frame"
        assert img.header.stamp.sec * 10**9 + img.header.stamp.nanosec == stamp
        decoded = cv2.imdecode(img.data, cv2.IMREAD_COLOR)
        assert np.abs(decoded.astype(int) - sent["Image"][i]["data"]).mean() < 3
        info = got["/camera/camera_info"][i][2]
        np.testing.assert_allclose(info.k.reshape(3, 3), K)
        np.testing.assert_allclose(info.p.reshape(3, 4)[:, :3], K)
        assert (info.width, info.height, info.distortion_model) == (W, H, "plumb_bob")
        hands = {h["handedness"]: h for h in sent["HandPose"][i]["hands"] if h["score"] > 0.6}   # the surer right
        tf = {t.child_frame_id: t for t in got["/tf"][i][2].transforms}
        assert len(tf) == 42
        for side, hand in hands.items():
            xyz, quat = hand["xyz"].astype(np.float64), hand["quat"].astype(np.float64)
            q = quat * [1, 1, -1, -1] if side == "left" else quat           # the mirrored model's, proper
            kp = got[f"/hand_{side}/keypoints"][i][2]
            pos = np.array([[p.position.x, p.position.y, p.position.z] for p in kp.poses])
            ori = np.array([[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w] for p in kp.poses])
            np.testing.assert_allclose(pos, xyz, atol=1e-6)
            np.testing.assert_allclose(ori, [xyzw(r) for r in q], atol=1e-6)
            wrist = got[f"/hand_{side}/wrist_pose"][i][2].pose
            np.testing.assert_allclose([wrist.position.x, wrist.position.y, wrist.position.z], xyz[0], atol=1e-6)
            # a finger joint's orientation turns the (mirrored) rest bone onto the posed bone
            rest = MODEL.rest_joints(hand["beta"].astype(np.float64))
            for j in (6, 7, 8, 11, 19):
                bone = rest[j] - rest[PARENTS[j]]
                bone = mirror_points(bone) if side == "left" else bone
                posed = xyz[j] - xyz[PARENTS[j]]
                np.testing.assert_allclose(quat_rotate(q[j], bone), posed, atol=2e-4)
            # the TF tree: composing camera -> wrist -> ... -> joint lands on every joint
            for j, name in enumerate(JOINT_NAMES):
                chain, k = [], j
                while k >= 0:
                    chain.append(tf[f"hand_{side}/{JOINT_NAMES[k]}"])
                    k = PARENTS[k]
                assert chain[-1].header.frame_id == "camera_optical_frame"
                p, r = np.zeros(3), np.array([1.0, 0, 0, 0])
                for t in reversed(chain):
                    tr, rot = t.transform.translation, t.transform.rotation
                    p = p + quat_rotate(r, [tr.x, tr.y, tr.z])
                    r = _mul(r, [rot.w, rot.x, rot.y, rot.z])
                np.testing.assert_allclose(p, xyz[j], atol=1e-6)
                np.testing.assert_allclose(np.abs(np.dot(r, q[j])), 1.0, atol=1e-6)
            js = got[f"/hand_{side}/joint_states"][i][2]
            assert len(js.name) == 45 and js.name[3 * 4] == f"hand_{side}/index_pip_flexion"
            np.testing.assert_allclose(js.position, limits.angles(hand["pose"].astype(np.float64)).reshape(-1),
                                       atol=1e-6)
        markers = {m.ns: m for m in got["/hand_markers"][i][2].markers}
        assert set(markers) == {f"hand_{s}/{k}" for s in hands for k in ("bones", "joints")}
        for side, hand in hands.items():
            bones = np.array([[p.x, p.y, p.z] for p in markers[f"hand_{side}/bones"].points]).reshape(-1, 2, 3)
            np.testing.assert_allclose(bones[:, 1], hand["xyz"][1:], atol=1e-6)       # each bone ends at its joint
            np.testing.assert_allclose(bones[:, 0], hand["xyz"][PARENTS[1:]], atol=1e-6)
            assert markers[f"hand_{side}/bones"].header.frame_id == "camera_optical_frame"
        robot = got["/robot_right/joint_states"][i][2]
        assert list(robot.name) == ["a", "b"]
        np.testing.assert_allclose(robot.position, [0.1 * i, -0.2])


def _mul(a, b):
    from handmocap.perception.rotations import quat_multiply
    return quat_multiply(np.asarray(a, float), np.asarray(b, float))


@pytest.mark.skipif(importlib.util.find_spec("mcap_ros2") is None, reason="mcap-ros2-support not installed")
def test_a_second_reader_decodes_every_message(exported):
    """mcap-ros2-support decodes the storage file with the schemas stored in it (no typestore):
    the same topics, counts and values."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    sent, folder = exported
    counts, keypoints = {}, []
    with open(folder / "out.mcap", "rb") as f:
        for _, channel, _, ros_msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == "/hand_left/keypoints":
                keypoints.append([[p.position.x, p.position.y, p.position.z] for p in ros_msg.poses])
    assert counts == {t: len(v) for t, v in rosbags_messages(folder).items()}
    for i, pos in enumerate(keypoints):
        left = [h for h in sent["HandPose"][i]["hands"] if h["handedness"] == "left"][0]
        np.testing.assert_allclose(pos, left["xyz"], atol=1e-6)


def test_an_existing_output_is_one_clear_error(exported, tmp_path, capsys):
    _, folder = exported
    assert handbag(["export", str(folder.parent / "src.mcap"), "--ros2", str(folder)]) == 1
    assert "already exists" in capsys.readouterr().err
