"""The Foxglove live bridge: its conversions in-process (every message fits its schema, the mesh
sits on the joints, frames, rate caps), and the bridge node in a real graph, checked by a plain
WebSocket client speaking Foxglove's protocol (no browser): serverInfo, advertise, subscribe,
binary messageData frames."""
import importlib.util
import json
import os
import socket
import struct
import subprocess
import sys
import time

import fastjsonschema
import numpy as np
import pytest

from conftest import graph_env
from graphnodes.pose_source import W, H, synthetic_pose_hands
from handmocap.perception import camera_info
from handmocap.runtime import codec
from handmocap.interop import foxglove_live as fl
from handmocap.runtime.frames import image_message
from handmocap.perception.hand_model import HandModel
from handmocap.perception.rotations import quat_to_matrix

MODEL = HandModel.load()
K = camera_info.default_K(W, H)
TOPICS = {"/camera/image": "Image", "/camera/info": "CameraInfo", "/hand/keypoints": "HandKeypoints",
          "/hand/pose": "HandPose"}
HAVE_FOXGLOVE = importlib.util.find_spec("foxglove") is not None
HAVE_WEBSOCKETS = importlib.util.find_spec("websockets") is not None
# foxglove-sdk 0.30 speaks "foxglove.sdk.v1" only (it answers HTTP 400 to "foxglove.websocket.v1"
# alone); older servers speak "foxglove.websocket.v1". Same messages, so a client offers both.
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


class FakeChannel:
    """Stands in for a foxglove.Channel: checks each message against the channel's schema."""

    def __init__(self, topic, schema, sinks=True):
        self.topic, self.schema, self.sinks, self.out = topic, schema, sinks, []
        self.validate = fastjsonschema.compile(schema)

    def has_sinks(self):
        return self.sinks

    def log(self, data, log_time):
        body = json.loads(data)
        self.validate(body)
        self.out.append((log_time, body))


def make_bridge(sinks=True, **params):
    channels = {}

    def make(topic, schema):
        channels[topic] = FakeChannel(topic, schema, sinks)
        return channels[topic]
    return fl.LiveBridge(TOPICS, make, MODEL, params), channels


def messages(handedness="right", n=3, stamp=1_700_000_000_123_456_789):
    """Decoded (topic, type, msg) of n frames, as the bridge node receives them."""
    out = []
    for i, (kp, pose) in enumerate(synthetic_pose_hands(n, 0, handedness, 4, [0.02, -0.01, 0.5], K, MODEL)):
        for topic, body in (("/camera/info", camera_info.camera_info_message(K, np.zeros(5), W, H, "default-fov")),
                            ("/camera/image", image_message(np.full((H, W, 3), 90, np.uint8))),
                            ("/hand/keypoints", {"width": W, "height": H, "hands": [kp]}),
                            ("/hand/pose", {"hands": [pose]})):
            wire = codec.encode({"header": codec.header(i, "camera", stamp + i), **body}, TOPICS[topic])
            out.append((topic, TOPICS[topic], codec.decode(wire, TOPICS[topic])))
    return out


@pytest.mark.parametrize("handedness", ["right", "left"])
def test_every_channel_gets_schema_valid_messages_and_the_mesh_sits_on_the_joints(handedness):
    bridge, channels = make_bridge(image_hz=1000, mesh_hz=1000)
    msgs = messages(handedness)
    for m in msgs:
        bridge.handle(*m)
    assert set(channels) == {*TOPICS, "/hand/pose/skeleton", "/hand/pose/mesh", "/tf"}
    assert all(c.out for c in channels.values()), {t: len(c.out) for t, c in channels.items()}
    pose_msg = [m for t, _, m in msgs if t == "/hand/pose"][0]
    hand = pose_msg["hands"][0]
    stamp = pose_msg["header"]["stamp_ns"]

    log_time, raw = channels["/hand/pose"].out[0]      # the raw pose, plottable: arrays as lists
    assert log_time == stamp and raw["header"]["stamp_ns"] == stamp
    (h,) = raw["hands"]
    assert h["handedness"] == handedness and h["track_id"] == 4
    np.testing.assert_allclose(h["xyz"], hand["xyz"], atol=1e-7)
    assert np.shape(h["quat"]) == (21, 4) and np.shape(h["pose"]) == (16, 3) and np.shape(h["beta"]) == (10,)

    _, mesh = channels["/hand/pose/mesh"].out[0]
    (entity,) = mesh["entities"]
    (tri,) = entity["triangles"]
    assert entity["frame_id"] == "camera" and entity["id"] == "hand/4/mesh"
    assert len(tri["points"]) == len(MODEL.v_template) and len(tri["indices"]) == 3 * len(MODEL.faces)
    vertices = np.array([[p["x"], p["y"], p["z"]] for p in tri["points"]])
    # the model posed at (quat, beta), moved by the same offset, puts its joints on xyz
    v_model, joints = MODEL.forward(hand["quat"], hand["beta"], handedness=handedness)
    offset = hand["root"] - joints[9]
    np.testing.assert_allclose(joints + offset, hand["xyz"], atol=1e-5)
    np.testing.assert_allclose(vertices, v_model + offset, atol=1e-4)   # rounded to 0.1 mm on the wire
    faces = np.array(tri["indices"]).reshape(-1, 3)
    np.testing.assert_array_equal(faces, MODEL.faces_for(handedness))

    _, skeleton = channels["/hand/pose/skeleton"].out[0]
    assert len(skeleton["entities"][0]["spheres"]) == 21

    (tf,) = [tf for t, tf in channels["/tf"].out if t == stamp and len(tf["transforms"]) == 2]
    by_child = {t["child_frame_id"]: t for t in tf["transforms"]}
    assert by_child["camera"]["parent_frame_id"] == "world"
    wrist = by_child["hand/4/wrist"]
    assert wrist["parent_frame_id"] == "camera"
    assert [wrist["translation"][k] for k in "xyz"] == pytest.approx(hand["xyz"][0].tolist(), abs=1e-6)
    q = [wrist["rotation"][k] for k in "wxyz"]
    R = quat_to_matrix(np.array(q))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-5)   # a proper frame, left hands too
    # the frame carries the (rigid) palm: the model's rest wrist -> middle MCP bone, mirrored for a
    # left hand, lands on the observed one
    rest = MODEL.rest_joints(hand["beta"])
    bone = (rest[9] - rest[0]) * ([-1, 1, 1] if handedness == "left" else 1)
    np.testing.assert_allclose(R @ bone, hand["xyz"][9] - hand["xyz"][0], atol=1e-5)


def test_world_frame_is_z_up_with_the_camera_looking_along_y():
    t = fl.camera_transform(5, "camera", "world")
    assert (t["parent_frame_id"], t["child_frame_id"]) == ("world", "camera")
    R = quat_to_matrix(np.array([t["rotation"][k] for k in "wxyz"]))
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 1, 0], atol=1e-12)    # camera forward: world +y
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, -1], atol=1e-12)   # camera down: world -z
    with pytest.raises(ValueError, match="camera_pose"):
        make_bridge(camera_pose=[0, 0, 0])


def test_rate_caps_and_idle_channels():
    bridge, channels = make_bridge(image_hz=1.0, mesh_hz=0.0)
    for m in messages(n=5):
        bridge.handle(*m)
    assert len(channels["/camera/image"].out) == 1       # 5 frames within far less than 1 s
    assert len(channels["/camera/info"].out) == 1
    assert len(channels["/hand/pose"].out) == len(channels["/hand/keypoints"].out) == 5   # never capped
    assert channels["/hand/pose/mesh"].out == []         # mesh_hz 0: off
    idle, idle_channels = make_bridge(sinks=False)
    for m in messages(n=2):
        idle.handle(*m)                                    # no client: nothing converted
    assert not any(c.out for c in idle_channels.values())


def test_rate_limit_keeps_the_average_rate_of_a_jittery_source():
    rate, rng = fl.RateLimit(), np.random.default_rng(0)
    times = np.arange(300) / 30 + rng.uniform(-0.01, 0.01, 300)        # 10 s of a 30 Hz camera, +-10 ms
    passed = [t for t in times if rate.allow("image", 15.0, now=t)]
    assert len(passed) == pytest.approx(150, abs=2)                     # every second frame
    assert rate.allow("image", 15.0, now=100.0) and not rate.allow("image", 15.0, now=100.01)   # no burst


# -- the node in a real graph ---------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def connect(port, deadline):
    from websockets.sync.client import connect as ws_connect
    while True:
        try:
            return ws_connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=5)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def message_data(frame: bytes):
    """A binary server frame -> (subscription id, log time ns, JSON payload); opcode 1 only."""
    opcode, sub_id, log_time = struct.unpack_from("<BIQ", frame)
    assert opcode == 1, opcode
    return sub_id, log_time, json.loads(frame[13:])


@pytest.mark.skipif(not HAVE_FOXGLOVE, reason="foxglove-sdk is not installed (the optional 'viz' extra)")
@pytest.mark.skipif(not HAVE_WEBSOCKETS, reason="the websockets client library is not installed (the 'test' extra)")
def test_bridge_node_serves_poses_to_a_websocket_client(tmp_path, run_dir):
    port = free_port()
    lf = tmp_path / "g.yaml"
    lf.write_text(f"""
nodes:
  pose_source: {{node: graphnodes.pose_source, params: {{hz: 20, handedness: left, track_id: 7}}}}
  bridge: {{node: bridge, params: {{port: {port}}}}}
""")
    proc = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=graph_env(run_dir),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        with connect(port, time.monotonic() + 60) as ws:
            assert ws.subprotocol in SUBPROTOCOLS
            info = json.loads(ws.recv(timeout=10))
            assert info["op"] == "serverInfo" and info["name"] == "handmocap"
            channels = {}
            want = {"/hand/pose", "/hand/pose/mesh", "/tf", "/camera/image"}
            while not want <= set(channels):       # channels may come in several advertise messages
                msg = json.loads(ws.recv(timeout=10))
                if msg["op"] == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
            pose_ch = channels["/hand/pose"]
            assert (pose_ch["encoding"], pose_ch["schemaEncoding"], pose_ch["schemaName"]) == \
                ("json", "jsonschema", "handmocap.HandPose")
            assert channels["/hand/pose/mesh"]["schemaName"] == "foxglove.SceneUpdate"
            assert channels["/camera/image"]["schemaName"] == "foxglove.CompressedImage"
            subs = {i: t for i, t in enumerate(sorted(want), start=1)}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": channels[t]["id"]} for i, t in subs.items()]}))
            got = {t: [] for t in want}
            deadline = time.monotonic() + 30
            while len(got["/hand/pose"]) < 5 or not all(got.values()):
                assert time.monotonic() < deadline, {t: len(v) for t, v in got.items()}
                frame = ws.recv(timeout=10)
                if isinstance(frame, bytes):
                    sub_id, log_time, body = message_data(frame)
                    got[subs[sub_id]].append((log_time, body))
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    assert f"serving the graph to Foxglove at ws://127.0.0.1:{port}" in out, out
    for log_time, pose in got["/hand/pose"]:
        assert log_time == pose["header"]["stamp_ns"] and pose["header"]["frame_id"] == "camera"
        (hand,) = pose["hands"]
        assert hand["handedness"] == "left" and hand["track_id"] == 7 and 0 <= hand["score"] <= 1
        shapes = {k: np.shape(hand[k]) for k in ("xyz", "root", "quat", "pose", "beta", "uv")}
        assert shapes == {"xyz": (21, 3), "root": (3,), "quat": (21, 4), "pose": (16, 3), "beta": (10,),
                          "uv": (21, 2)}
        assert np.linalg.norm(hand["quat"], axis=1) == pytest.approx(np.ones(21), abs=1e-5)
        assert hand["root"] == pytest.approx([0.02, -0.01, 0.5], abs=0.02)   # where the source put it
    seqs = [p["header"]["seq"] for _, p in got["/hand/pose"]]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    _, mesh = got["/hand/pose/mesh"][0]
    assert len(mesh["entities"][0]["triangles"][0]["points"]) == len(MODEL.v_template)
    _, image = got["/camera/image"][0]
    assert image["format"] == "jpeg" and image["frame_id"] == "camera"
    children = {t["child_frame_id"] for _, tf in got["/tf"] for t in tf["transforms"]}
    assert {"camera", "hand/7/wrist"} <= children


def run_bridge(run_dir, *args, prelude=""):
    """The bridge node run by hand (outside a launched graph), with `prelude` Python run first."""
    code = f"{prelude}\nimport runpy, sys\nsys.argv = ['bridge', *{list(args)!r}]\n" \
           "runpy.run_module('handmocap.nodes.bridge', run_name='__main__')"
    return subprocess.run([sys.executable, "-c", code], env={**os.environ, "HANDMOCAP_RUN_DIR": str(run_dir)},
                          capture_output=True, text=True, timeout=60)


@pytest.mark.skipif(not HAVE_FOXGLOVE, reason="foxglove-sdk is not installed (the optional 'viz' extra)")
def test_port_taken_is_one_clear_error_line(run_dir):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        r = run_bridge(run_dir, f"port:={s.getsockname()[1]}")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "port is already in use" in lines[0] and "port:=" in lines[0], r.stderr


def test_missing_foxglove_sdk_is_one_clear_error_line(run_dir):
    r = run_bridge(run_dir, prelude="import sys; sys.modules['foxglove'] = None   # as if not installed")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "foxglove-sdk" in lines[0] and "[viz]" in lines[0], r.stderr
