"""No message, however malformed, stops a node (issue 30): the codec raises only
MalformedMessage, on every message type; the four inputs that once stopped a whole graph are
dropped and counted with the graph running on; a handler that fails on a message loses only
that message."""
import time

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from conftest import handlaunch, paths_in
from graphnodes.killers import image_killers, nan_keypoints
from handmocap.runtime import codec
from handmocap.runtime.bag import iter_messages
from handmocap.runtime.node import Node


def test_the_four_killers_are_malformed_messages():
    reasons = {}
    for name, payload in image_killers(1_700_000_000_000_000_000):
        with pytest.raises(codec.MalformedMessage) as e:
            codec.decode(payload, "Image")
        reasons[name] = e.value.reason
    assert reasons == {"1-D data": "inconsistent", "(0,0,3) data": "inconsistent",
                       "huge array": "array-shape", "nested 1,000 deep": "too-deep"}
    with pytest.raises(codec.MalformedMessage, match="not-finite"):
        codec.decode(nan_keypoints(0), "HandKeypoints")


def sample(type_name):
    """A valid message of each type (its wire form, before msgpack)."""
    h = codec.header(3)
    f32 = lambda *s: np.zeros(s, np.float32)
    hand_kp = {"track_id": 1, "handedness": "left", "score": 0.5, "bbox": f32(4), "uv": f32(21, 2),
               "confidence": f32(21), "xyz_rel": f32(21, 3)}
    hand_pose = {"track_id": 1, "handedness": "right", "score": 0.5, "xyz": f32(21, 3), "root": f32(3),
                 "quat": np.tile(np.float32([1, 0, 0, 0]), (21, 1)), "pose": f32(16, 3), "beta": f32(10),
                 "uv": f32(21, 2)}
    bodies = {
        "Image": {"encoding": "bgr8", "width": 4, "height": 2, "data": np.zeros((2, 4, 3), np.uint8)},
        "CameraInfo": {"width": 4, "height": 2, "K": np.eye(3), "distortion": np.zeros(5)},
        "HandKeypoints": {"width": 4, "height": 2, "hands": [hand_kp]},
        "HandPose": {"hands": [hand_pose]},
        "HandShape": {"shapes": [{"track_id": 1, "handedness": "left", "beta": f32(10), "rest_xyz": f32(21, 3),
                                  "bone_ratios": f32(20), "samples": 3}]},
        "HandMesh": {"hands": [{"track_id": 1, "handedness": "left", "vertices": f32(5, 3)}]},
        "RobotJointStates": {"robots": [{"handedness": "left", "track_id": 1, "robot": "toy", "name": ["a"],
                                         "position": np.zeros(1)}]},
        "Blob": {"data": np.zeros(8, np.uint8)},
    }
    return {"header": h, **bodies[type_name]}


def test_every_type_has_a_valid_sample():
    assert set(codec.message_types()) <= {"Image", "CameraInfo", "HandKeypoints", "HandPose", "HandShape",
                                          "HandMesh", "RobotJointStates", "Blob"}
    for t in codec.message_types():
        codec.decode(codec.encode(sample(t), t), t)


def wire(obj):
    """The message with its arrays in wire form (what msgpack carries)."""
    return msgpack.unpackb(codec.encode(obj), raw=False)


leaves = (st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=6)
          | st.binary(max_size=24)
          | st.builds(lambda d, s, n: {"dtype": d, "shape": s, "data": bytes(n)},
                      st.sampled_from(["uint8", "float32", "int64", "bool", "complex64", 7]),
                      st.lists(st.integers(-1, 2**64 - 1) | st.floats(0, 4), max_size=4), st.integers(0, 64)))
structures = st.recursive(leaves, lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=6), c, max_size=3),
                          max_leaves=12)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(sorted(codec.message_types())), st.data())
def test_structured_fuzz_of_every_type_only_ever_raises_malformed(type_name, data):
    """A valid message of the type with one part replaced by anything (a deeply nested list, an
    array of absurd shape, a wrong type), or an extra key, or its payload cut or flipped."""
    msg = wire(sample(type_name))
    paths = [p for p in paths_in(msg) if p]
    how = data.draw(st.sampled_from(["replace", "extra", "deep", "bytes"]))
    if how == "replace":
        path = data.draw(st.sampled_from(paths))
        parent = msg
        for k in path[:-1]:
            parent = parent[k]
        parent[path[-1]] = data.draw(structures)
    elif how == "extra":
        msg[data.draw(st.text(max_size=6))] = data.draw(structures)
    elif how == "deep":
        deep = leaf = []
        for _ in range(data.draw(st.integers(100, 1000))):   # msgpack packs at most ~1,000 deep
            leaf.append([])
            leaf = leaf[0]
        msg[data.draw(st.sampled_from(list(msg)))] = deep
    payload = msgpack.packb(msg)
    if how == "bytes":
        payload = bytearray(payload)
        for _ in range(data.draw(st.integers(1, 8))):
            payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
        payload = bytes(payload)[:data.draw(st.integers(1, len(payload)))]
    try:
        out = codec.decode(payload, type_name)
    except codec.MalformedMessage:
        return
    assert isinstance(out, dict) and "header" in out


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_killers_are_dropped_and_counted_with_the_graph_running_on(tmp_path, run_dir):
    """killers -> detector -> shape -> ik, and a recorder of everything: every good frame gets its
    keypoints and pose, every killer is dropped by each subscriber (one warning per cause and
    a counter), the NaN keypoints by ik, and the graph ends normally."""
    bag = tmp_path / "k.mcap"
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  killers: {{node: graphnodes.killers, params: {{frames: 20}}, required: true}}
  detector: {{node: detector, params: {{every_frame: true}}, required: true}}
  shape: {{node: shape}}
  ik: {{node: ik, required: true}}
  recorder: {{node: recorder, params: {{output: "{bag}", raw: true}}, required: true}}
""")
    r = handlaunch([lf], run_dir, timeout=120)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert "Traceback" not in out
    counts = {}
    for topic, _, _, _ in iter_messages(bag):
        counts[topic] = counts.get(topic, 0) + 1
    assert counts["/camera/image"] == 20 and counts["/hand/pose"] == 20
    for node in ("detector", "recorder"):
        for cause in ("inconsistent: bgr8 image 64x48 needs data", "numpy refuses shape", "too-deep"):
            assert any(line.startswith(f"[{node}] WARNING dropped") and cause in line for line in out.splitlines()), \
                (node, cause, out)
    assert any(line.startswith("[ik] WARNING dropped") and "not-finite" in line for line in out.splitlines()), out


def test_a_handler_that_fails_drops_only_that_message(tmp_path, monkeypatch):
    from handmocap.runtime.node import Message, Node
    monkeypatch.setenv("HANDMOCAP_RUN_DIR", str(tmp_path / "run"))
    node = Node("handler_test", params={}, argv=[])
    seen = []

    def handler(msg):
        if msg.data["n"] == 2:
            raise KeyError("boom")
        seen.append(msg.data["n"])
    try:
        for n in range(5):
            node.handle(handler, Message("/t", "Blob", {"n": n}, b"", 0))
        assert seen == [0, 1, 3, 4]
        assert node.stats["dropped"] == {"/t:handler-KeyError": 1}
    finally:
        node.close()


# ------------------------------------------------------------------ values, not only shapes (issue 49)
def _float_paths(obj, path=""):
    """Paths (as codec.non_finite names them) of every float and float array of a message."""
    if isinstance(obj, np.ndarray):
        return [path] if obj.dtype.kind == "f" else []
    if isinstance(obj, float):
        return [path]
    if isinstance(obj, dict):
        return [p for k, v in obj.items() for p in _float_paths(v, f"{path}.{k}" if path else k)]
    if isinstance(obj, list):
        return [p for i, v in enumerate(obj) for p in _float_paths(v, f"{path}[{i}]")]
    return []


def _set(obj, path, value):
    import re
    keys = [int(k) if k.isdigit() else k for k in re.findall(r"[^.\[\]]+", path)]
    for k in keys[:-1]:
        obj = obj[k]
    obj[keys[-1]] = value(obj[keys[-1]])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_every_float_of_every_type_must_be_finite(bad):
    """A NaN or inf in any float field or array of any type (a HandShape's beta, a keypoint's
    score) is refused, naming where: as not finite, or by the bounds a field has in its schema
    (no comparison holds for NaN)."""
    import copy
    checked = 0
    for t in codec.message_types():
        for path in _float_paths(sample(t)):
            msg = copy.deepcopy(sample(t))
            _set(msg, path, lambda v: np.where(np.ones_like(v, bool), bad, v).astype(v.dtype)
                 if isinstance(v, np.ndarray) else bad)
            with pytest.raises(codec.MalformedMessage) as e:
                codec.decode(codec.encode(msg, None), t)
            assert e.value.reason in ("not-finite", "schema") and path in str(e.value), (t, path, e.value)
            checked += 1
    assert checked >= 19          # score, bbox, uv, K, beta, vertices, position, ...


def test_a_stamp_from_the_future_is_refused():
    msg = sample("HandPose")
    msg["header"]["stamp_ns"] = 2**64 - 1
    with pytest.raises(codec.MalformedMessage, match="stamp-future"):
        codec.decode(codec.encode(msg, None), "HandPose")
    msg["header"]["stamp_ns"] = time.time_ns() + codec.MAX_FUTURE_NS // 2       # a host's clock a little ahead
    codec.decode(codec.encode(msg, None), "HandPose")


def test_a_non_finite_result_is_dropped_at_the_source_and_counted(run_dir):
    """A node about to publish a NaN drops it (counted, logged naming the input it came from)
    and spends no seq on it, so no subscriber counts a loss."""
    pub = Node("src", argv=[])
    pub.advertise("/pose", "HandPose")
    bad = sample("HandPose")
    bad["hands"][0]["beta"] = np.full(10, np.nan, np.float32)
    pub.publish("/pose", {"hands": bad["hands"]})
    assert pub.stats["dropped"]["/pose:not-finite-out"] == 1 and pub.seq["/pose"] == 0
    pub.close()


def test_a_restart_a_stray_seq_or_a_second_frame_id_is_no_loss(run_dir, caplog):
    """Keep-all loss counting (Node._count_lost) on the drill's sequences: a stray seq 0 in a
    stream at 3,320, a publisher that restarts, and one topic carrying two frame_ids (a
    publisher numbers a topic's messages whatever their frame) lose nothing; a real gap of
    9 is 9 lost, and the warning names the jump."""
    node = Node("loss_test", argv=[])
    seen = lambda topic, seqs, frames=("camera",): [node._count_lost(topic, {"seq": s, "frame_id": frames[i % len(frames)]})
                                                   for i, s in enumerate(seqs)]
    seen("/a", [*range(3300, 3321), 0, *range(3321, 3400)])                   # a forged seq 0 in the middle
    seen("/b", [*range(0, 50), *range(0, 50)])                                # the publisher restarted
    seen("/c", range(0, 100), frames=("camera", "camera2"))                   # two frame ids, one seq counter
    assert not any(node.stats["lost"].values()), dict(node.stats["lost"])
    seen("/e", [*range(0, 10), *range(19, 30)])                               # a real gap
    assert dict(node.stats["lost"]) == {"/e": 9}
    assert "seq 19 after 9" in caplog.text
    node.close()



def test_non_finite_names_the_first_bad_value_in_any_container_and_passes_finite_ones():
    """The fast check (all float arrays in one numpy call) and the walk that names the place
    agree: one bad element of one array, a NaN in a dict subclass or a numpy float, a view."""
    from collections import OrderedDict
    ok = {"a": [1.0, {"b": np.zeros(3, np.float32)}], "n": np.arange(3), "s": "x", "z": None,
          "v": np.zeros((2, 3))[:, ::2]}
    assert codec.non_finite(ok) is None
    assert codec.non_finite({**ok, "c": np.array([0, 0, np.inf], np.float32)}) == "c"
    assert codec.non_finite({"a": [1.0, {"b": np.array([0, -np.inf], np.float32)}]}) == "a[1].b"
    assert codec.non_finite({"a": OrderedDict(x=float("nan"))}) == "a.x"
    assert codec.non_finite({"a": [np.float64("nan")]}) == "a[0]"
    assert codec.non_finite({"v": np.array([[np.nan, 0.0], [0.0, 0.0]])[:, 1:]}) is None   # the NaN is not in the view
    cyclic = {"x": 1.0}
    cyclic["self"] = cyclic                  # a body that holds itself: an error, never a hang
    with pytest.raises(RecursionError):
        codec.non_finite(cyclic)
