"""Live in ROS 2 (issue 48), real processes on real DDS (rclpy and Fast DDS from PyPI):
- a replayed clip -> the graph with the `ros2` node -> a plain rclpy subscriber in another
  process (examples/ros2_listen_hands.py): every /hand/pose's hands arrive, values equal to
  /hand/pose's and to `handbag export --ros2` of the same run's bag;
- a plain rclpy publisher of sensor_msgs/Image (examples/ros2_publish_video.py) ->
  `ros2_camera` -> launch/ros2.yaml's whole graph -> hands back on ROS 2, every frame
  accounted for.
The clip is a real one from ../shared (a webcam clip of a stranger) when present, else the
project's rendered demo clip. Each test runs in its own ROS_DOMAIN_ID.
"""
import importlib.util
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import DEMO_CLIP, ROOT, SHARED_DATA, chain_yaml, graph_env, read_bag

pytestmark = pytest.mark.skipif(importlib.util.find_spec("rclpy") is None,
                                reason="ROS 2's rclpy not installed (pip install -e '.[ros2]')")
REAL_CLIP = SHARED_DATA / "video" / "webcam" / "alimostafa_hand.mp4"   # 352x640, 30 fps, one stranger's hand
CLIP = REAL_CLIP if REAL_CLIP.exists() else DEMO_CLIP
FRAMES = 60
SIDES = ("right", "left")


def ros_env(run_dir, domain):
    env = graph_env(run_dir, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)          # the nodes' own loopback profile, not a user's
    return env


def start_listener(path, env):
    """examples/ros2_listen_hands.py writing every message's values to `path` (JSON lines),
    its stderr to path + ".err"; returns once it listens."""
    err = path.with_suffix(".err")
    proc = subprocess.Popen([sys.executable, str(ROOT / "examples" / "ros2_listen_hands.py"), "--jsonl", str(path),
                             "--seconds", "120"], env=env, stderr=open(err, "w"), text=True)
    deadline = time.monotonic() + 30
    while "listening" not in err.read_text():
        assert proc.poll() is None and time.monotonic() < deadline, err.read_text()
        time.sleep(0.05)
    return proc


def stop(proc):
    proc.terminate()
    proc.wait(timeout=20)


def udp_sockets(pid):
    """[(local IPv4 address, port)] of the UDP sockets process `pid` holds (/proc)."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    out = []
    for line in open(f"/proc/{pid}/net/udp").read().splitlines()[1:]:
        fields = line.split()
        if fields[9] in inodes:
            ip_hex, port_hex = fields[1].split(":")
            out.append((".".join(str(b) for b in bytes.fromhex(ip_hex)[::-1]), int(port_hex, 16)))
    return out


def received(path):
    """{(topic, stamp_ns): values} of the listener's lines; asserts no (topic, stamp) came twice."""
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    out = {(m["topic"], m["stamp_ns"]): m for m in lines}
    assert len(out) == len(lines)
    return out


def expected(pose):
    """{(topic, stamp): HandPose hand} of what the ros2 node publishes for one /hand/pose."""
    from handmocap.perception.pose import surest_per_side
    stamp = pose["header"]["stamp_ns"]
    return {(f"/hand_{side}/{suffix}", stamp): (side, hand) for side, hand in surest_per_side(pose["hands"]).items()
            for suffix in ("joint_states", "keypoints", "wrist_pose")}


def export_values(bag_path, tmp_path):
    """{(topic, stamp): rosbags message} of `handbag export --ros2` of the run's bag."""
    from rosbags.rosbag2 import Reader

    from handmocap.interop.bag_cli import main as handbag
    from handmocap.interop.ros2_messages import typestore
    assert handbag(["export", str(bag_path), "--ros2", str(tmp_path / "ros2bag")]) == 0
    ts, out = typestore(), {}
    with Reader(tmp_path / "ros2bag") as reader:
        for conn, _, raw in reader.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            header = msg.markers[0].header if conn.topic == "/hand_markers" else getattr(msg, "header", None)
            if header is not None:
                out[(conn.topic, header.stamp.sec * 10**9 + header.stamp.nanosec)] = msg
    return out


def check_values(got, poses, exported):
    """Every hand of every pose arrived once, equal to the pose and to the bag export."""
    from handmocap.perception.hand_model import HandModel
    from handmocap.perception.joint_limits import JointLimits
    from handmocap.perception.skeleton import PARENTS
    limits = JointLimits.for_model(HandModel.load())
    want = {k: v for pose in poses for k, v in expected(pose).items()}
    assert want, "no hand in any pose: nothing to compare"
    hand_keys = {k for k in got if k[0] != "/hand_markers"}
    assert hand_keys == set(want), f"{len(hand_keys)} hand messages received of {len(want)}"
    for (topic, stamp), (side, hand) in want.items():
        m, e = got[(topic, stamp)], exported[(topic, stamp)]
        xyz = np.asarray(hand["xyz"], np.float64)
        if topic.endswith("joint_states"):
            np.testing.assert_allclose(m["position"], limits.angles(np.asarray(hand["pose"], np.float64)).ravel(),
                                       atol=1e-9)
            np.testing.assert_array_equal(m["position"], e.position)
            assert m["name"] == list(e.name)
        elif topic.endswith("keypoints"):
            np.testing.assert_allclose(m["xyz"], xyz, atol=1e-9)
            np.testing.assert_array_equal(m["xyz"], [[p.position.x, p.position.y, p.position.z] for p in e.poses])
        else:
            np.testing.assert_allclose(m["xyz"], xyz[0], atol=1e-9)
        marker = got[("/hand_markers", stamp)]["markers"][f"hand_{side}/bones"]
        bones = np.asarray(marker).reshape(-1, 2, 3)
        np.testing.assert_allclose(bones[:, 0], xyz[PARENTS[1:]], atol=1e-9)
        np.testing.assert_allclose(bones[:, 1], xyz[1:], atol=1e-9)


def test_a_replayed_clip_reaches_a_plain_rclpy_subscriber(tmp_path, run_dir):
    domain = 20 + os.getpid() % 50
    env = ros_env(run_dir, domain)
    listener = start_listener(tmp_path / "hands.jsonl", env)
    try:
        lf = tmp_path / "g.yaml"
        lf.write_text(chain_yaml(CLIP, tmp_path / "run.mcap", rate=1.0, replay_params=f", duration: {FRAMES / 30}",
                                 extra_nodes="  ros2: {node: ros2, required: true, params: {wait_for_subscriber_s: 20}}"))
        r = subprocess.run([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=env,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stdout + r.stderr
        time.sleep(1.0)                         # the last messages on their way
    finally:
        stop(listener)
    poses = [m for m, _ in read_bag(tmp_path / "run.mcap")["/hand/pose"]]
    assert len(poses) >= FRAMES - 1
    check_values(received(tmp_path / "hands.jsonl"), poses, export_values(tmp_path / "run.mcap", tmp_path))
    assert "/tf not published" in r.stdout + r.stderr          # tf2_msgs is not on PyPI: said once


def test_a_ros2_camera_feeds_the_graph_and_every_frame_comes_back(tmp_path, run_dir):
    domain = 70 + os.getpid() % 25
    env = ros_env(run_dir, domain)
    listener = start_listener(tmp_path / "hands.jsonl", env)
    graph = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(ROOT / "launch" / "ros2.yaml"),
                              "every_frame:=true", "timeout_s:=3", f"bag:={tmp_path / 'run.mcap'}"],
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60        # the ros2 node found (DDS discovery: 0.1-2 s) before any frame
        while "matched /hand_right/joint_states" not in (tmp_path / "hands.err").read_text():
            assert graph.poll() is None and time.monotonic() < deadline, (tmp_path / "hands.err").read_text()
            time.sleep(0.05)
        # safe by default: the ros2 node's DDS ports of its domain (RTPS: 7400 + 250 domain + ...)
        # receive on the loopback interface only
        pid = json.loads((run_dir / "ros2.json").read_text())["pid"]
        rtps = [(ip, port) for ip, port in udp_sockets(pid) if 7400 + 250 * domain <= port < 7650 + 250 * domain]
        assert rtps and all(ip == "127.0.0.1" for ip, _ in rtps), rtps
        camera = subprocess.run([sys.executable, str(ROOT / "examples" / "ros2_publish_video.py"), str(CLIP),
                                 "--frames", str(FRAMES), "--stamps", str(tmp_path / "stamps.txt")],
                                env=env, capture_output=True, text=True, timeout=120)
        assert camera.returncode == 0, camera.stderr
        out, _ = graph.communicate(timeout=120)
        assert graph.returncode == 0, out
        time.sleep(1.0)
    finally:
        if graph.poll() is None:
            graph.terminate()
            graph.wait(timeout=30)
        stop(listener)
    sent = [int(s) for s in (tmp_path / "stamps.txt").read_text().split()]
    bag = read_bag(tmp_path / "run.mcap")
    assert len(sent) == FRAMES
    # every ROS frame entered the graph once, with its ROS stamp, and got a pose
    assert [m["header"]["stamp_ns"] for m, _ in bag["/camera/image"]] == sent
    poses = [m for m, _ in bag["/hand/pose"]]
    assert [p["header"]["stamp_ns"] for p in poses] == sent
    assert f"after {FRAMES}: end of stream" in out
    got = received(tmp_path / "hands.jsonl")
    assert sum(1 for p in poses if p["hands"]) >= FRAMES * 0.8, "the clip shows a hand in (almost) every frame"
    check_values(got, poses, export_values(tmp_path / "run.mcap", tmp_path))


def test_a_best_effort_camera_is_taken_too(tmp_path, run_dir):
    """A driver that publishes best effort (sensor-data QoS) is matched too (a reliable
    subscription would get nothing from it): its JPEG frames on .../compressed arrive, every
    one here when the suite runs alone (raw 640x480 frames best effort mostly do not: Fast DDS
    fragments them, and 5-8 of 30 came through on this host; docs/reference.md). In the full
    suite on a slower 2-core machine 27 of 30 came, 1 run in 4: best effort may lose a frame
    (which ones: the failure says), and what is under test is that the driver is matched at
    all (a reliable subscription gets none of its frames), so 24 of 30 is the bound."""
    env = ros_env(run_dir, 10 + os.getpid() % 10)
    graph = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(ROOT / "launch" / "ros2.yaml"),
                              "image_topic:=/camera/image_raw/compressed", "every_frame:=true", "timeout_s:=2",
                              "images:=false", f"bag:={tmp_path / 'run.mcap'}"],
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        camera = subprocess.run([sys.executable, str(ROOT / "examples" / "ros2_publish_video.py"), str(DEMO_CLIP),
                                 "--frames", "30", "--best-effort", "--compressed", "--stamps", str(tmp_path / "sent")],
                                env=env, capture_output=True,
                                text=True, timeout=120)
        assert camera.returncode == 0, camera.stderr
        out, _ = graph.communicate(timeout=120)
    finally:
        if graph.poll() is None:
            graph.terminate()
            graph.wait(timeout=30)
    assert graph.returncode == 0, out
    assert "taking /camera/image_raw/compressed best effort" in out, out
    taken = {m["header"]["stamp_ns"] for m, _ in read_bag(tmp_path / "run.mcap")["/camera/image"]}
    sent = [int(line) for line in (tmp_path / "sent").read_text().split()]
    missing = [i for i, stamp in enumerate(sent) if stamp not in taken]
    assert len(sent) == 30 and len(missing) <= 6, (f"frames {missing} of 30 lost", out)


# ------------------------------------------------------------------ the pieces, in-process
def test_ros_images_become_the_graphs_images():
    import cv2
    from sensor_msgs.msg import CompressedImage, Image

    from handmocap.interop.ros2_live import image_body
    frame = np.random.default_rng(0).integers(0, 255, (5, 7, 3), np.uint8)
    padded = np.zeros((5, 24), np.uint8)                               # rows padded to 24 bytes (step)
    padded[:, :21] = frame.reshape(5, 21)
    body = image_body(Image(height=5, width=7, encoding="bgr8", step=24, data=padded.tobytes()))
    assert body["encoding"] == "bgr8" and (body["width"], body["height"]) == (7, 5)
    np.testing.assert_array_equal(body["data"], frame)
    rgba = np.concatenate([frame[..., ::-1], np.full((5, 7, 1), 255, np.uint8)], -1)
    np.testing.assert_array_equal(image_body(Image(height=5, width=7, encoding="rgba8", step=28,
                                                   data=rgba.tobytes()))["data"], frame)
    mono = image_body(Image(height=5, width=7, encoding="mono8", step=7, data=frame[..., 0].tobytes()))
    assert mono["encoding"] == "mono8" and mono["data"].shape == (5, 7)
    png = cv2.imencode(".png", frame)[1].tobytes()
    np.testing.assert_array_equal(image_body(CompressedImage(format="png", data=png))["data"], frame)
    with pytest.raises(ValueError, match="16UC1"):
        image_body(Image(height=5, width=7, encoding="16UC1", step=14, data=bytes(70)))
    with pytest.raises(ValueError, match="step 21"):
        image_body(Image(height=5, width=7, encoding="bgr8", step=21, data=bytes(50)))
    with pytest.raises(ValueError, match="can't decode"):
        image_body(CompressedImage(format="jpeg", data=b"not a jpeg"))


def test_ros_camera_info_and_names():
    from sensor_msgs.msg import CameraInfo

    from handmocap.interop.ros2_live import info_body
    from handmocap.nodes.ros2_camera import check_params, info_topic_for
    K = [500.0, 0, 320, 0, 510, 240, 0, 0, 1]
    body = info_body(CameraInfo(width=640, height=480, k=K, d=[0.1, -0.2, 0, 0, 0.01]))
    np.testing.assert_array_equal(body["K"], np.reshape(K, (3, 3)))
    assert list(body["distortion"]) == [0.1, -0.2, 0, 0, 0.01] and body["source"] == "ros2"
    with pytest.raises(ValueError, match="camera matrix"):
        info_body(CameraInfo(width=640, height=480))                   # k all zero: an uncalibrated driver
    assert info_topic_for("/camera/image_raw") == "/camera/camera_info"
    assert info_topic_for("/oak/rgb/image_raw/compressed") == "/oak/rgb/camera_info"
    for bad, word in (({"image_topic": ""}, "image_topic"), ({"discovery": "internet"}, "discovery"),
                      ({"reliable": "yes"}, "reliable"), ({"timeout_s": 0}, "timeout_s")):
        with pytest.raises(ValueError, match=word):
            check_params(bad)


def test_rclpy_definitions_are_checked_against_rosbags():
    """CDR bytes are only published where rclpy's definition has rosbags' fields in order."""
    from geometry_msgs.msg import PoseArray
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import MarkerArray

    from handmocap.interop.ros2_live import ros_class, same_fields
    from handmocap.interop.ros2_messages import TOPICS, typestore
    ts = typestore()
    for cls, msgtype in ((JointState, "sensor_msgs/msg/JointState"), (PoseArray, "geometry_msgs/msg/PoseArray"),
                         (MarkerArray, "visualization_msgs/msg/MarkerArray")):
        assert same_fields(cls, ts, msgtype)
    assert not same_fields(JointState, ts, "geometry_msgs/msg/PoseArray")
    assert ros_class("tf2_msgs/msg/TFMessage") is None or same_fields(ros_class("tf2_msgs/msg/TFMessage"), ts,
                                                                       "tf2_msgs/msg/TFMessage")
    assert {t for t, m in TOPICS.items() if ros_class(m) is None} <= {"/tf"}
