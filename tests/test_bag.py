"""Bags: MCAP round trip, crash tolerance, handbag info/export/play, the recorder node."""
from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from handmocap.runtime import bag, bus, codec
from handmocap.interop.bag_cli import main as handbag
from handmocap.runtime.frames import frame_bgr
from handmocap.perception.skeleton import BONES

T0 = 1_700_000_000_000_000_000   # ns, a fixed epoch for stamps in synthetic bags


def image_payload(seq: int, h: int = 48, w: int = 64) -> bytes:
    img = np.zeros((h, w, 3), np.uint8)
    img[:, : (seq * 7) % w] = (255, 128, seq % 256)
    return codec.encode({"header": codec.header(seq, stamp_ns=T0 + seq * 33_000_000),
                         "encoding": "bgr8", "width": w, "height": h, "data": img}, "Image")


def blob_payload(seq: int, size: int = 100) -> bytes:
    data = np.frombuffer(np.random.default_rng(seq).bytes(size), np.uint8)
    return codec.encode({"header": codec.header(seq, stamp_ns=T0 + seq * 1_000_000), "data": data}, "Blob")


def hand(rng, handedness="right"):
    return {"track_id": 3, "handedness": handedness, "score": 0.75,
            "bbox": np.array([5, 6, 40, 44], np.float32),
            "uv": (rng.random((21, 2)) * 40).astype(np.float32),
            "confidence": np.ones(21, np.float32),
            "xyz_rel": rng.random((21, 3)).astype(np.float32)}


def write_sample_bag(path: Path, extra_frames: int = 0) -> list[tuple[str, str, bytes]]:
    """Five frames of every exported type, then `extra_frames` 320x240 images; returns
    [(topic, type, payload)] in write order."""
    rng = np.random.default_rng(1)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    written = []
    with bag.BagWriter(path) as w:
        for i in range(5):
            stamp = T0 + i * 33_000_000
            h = codec.header(i, stamp_ns=stamp)
            msgs = [
                ("/camera/image", "Image", image_payload(i)),
                ("/camera/info", "CameraInfo", codec.encode(
                    {"header": h, "width": 64, "height": 48, "K": K, "distortion": np.zeros(5)}, "CameraInfo")),
                ("/hand/keypoints", "HandKeypoints", codec.encode(
                    {"header": h, "width": 64, "height": 48, "hands": [hand(rng), hand(rng, "left")]},
                    "HandKeypoints")),
                ("/hand/pose", "HandPose", codec.encode(
                    {"header": h, "hands": [{
                        "track_id": 3, "handedness": "right", "score": 0.5,
                        "xyz": rng.random((21, 3)).astype(np.float32), "root": np.zeros(3, np.float32),
                        "quat": np.tile(np.float32([1, 0, 0, 0]), (21, 1)),
                        "pose": np.zeros((16, 3), np.float32),
                        "beta": np.linspace(-1, 1, 10).astype(np.float32),
                        "uv": np.zeros((21, 2), np.float32)}]}, "HandPose")),
                ("/test/blob", "Blob", blob_payload(i)),
            ]
            for k, (topic, type_name, payload) in enumerate(msgs):
                w.write(topic, type_name, payload, stamp + 1000 + k, stamp)
                written.append((topic, type_name, payload))
        for i in range(extra_frames):
            written.append(("/camera/image", "Image", image_payload(i, 240, 320)))
            w.write(*written[-1], T0 + 10**9 + i, T0 + 10**9 + i)
    return written


def run_handbag(*args: str, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "handmocap.interop.bag_cli", *args], capture_output=True,
                          text=True, timeout=60, env=env)


# -- reading and writing --------------------------------------------------------------------
def test_round_trip_is_byte_identical(tmp_path):
    path = tmp_path / "rt.mcap"
    written = write_sample_bag(path)
    read = [(t, ty, p) for t, ty, p, _ in bag.iter_messages(path)]
    assert read == written
    only = [(t, p) for t, _, p, _ in bag.iter_messages(path, topics=["/test/blob"])]
    assert only == [(t, p) for t, _, p in written if t == "/test/blob"]
    info = bag.bag_info(path)
    assert not info["truncated"] and info["unreadable_bytes"] == 0
    assert info["message_count"] == 25
    assert info["topics"]["/camera/image"] == {"type": "Image", "count": 5, "encoding": "msgpack"}
    assert info["start_ns"] == T0 + 1000 and info["end_ns"] == T0 + 4 * 33_000_000 + 1004
    # the standard reader agrees: schema = the wire JSON Schema, encoding msgpack
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert channel.message_encoding == "msgpack" and schema.encoding == "jsonschema"
            assert json.loads(schema.data) == codec.schema(schema.name)


def test_a_long_recording_keeps_no_chunk_index_in_memory_and_its_summary_has_them_all(tmp_path):
    """Chunks close every 256 kB: their indexes go to a temporary file as they close (the
    writer's memory stays flat over hours) and come back into the summary at close, where
    the standard mcap reader finds every chunk, in order, and every message."""
    path = tmp_path / "long.mcap"
    payload = bytes(range(256)) * 80                   # ~20 kB, a JPEG frame's size
    with bag.BagWriter(path) as w:
        for i in range(3000):
            w.write("/camera/image", "Image", payload, i, i)
            assert len(w._chunk_indexes) <= 1          # spilled as each chunk closes
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        starts = [c.chunk_start_offset for c in summary.chunk_indexes]
        assert len(starts) == summary.statistics.chunk_count > 200 and starts == sorted(starts)
        assert [m.log_time for _, _, m in reader.iter_messages()] == list(range(3000))


@pytest.mark.parametrize("cut", [-1, -37, 0.5, 0.1])
def test_cut_file_reads_up_to_last_complete_record(tmp_path, cut):
    full, part = tmp_path / "full.mcap", tmp_path / "part.mcap"
    written = write_sample_bag(full)
    data = full.read_bytes()
    n = len(data) + cut if isinstance(cut, int) else int(len(data) * cut)
    part.write_bytes(data[:n])
    read = [(t, ty, p) for t, ty, p, _ in bag.iter_messages(part)]
    assert read == written[: len(read)]          # a prefix, nothing garbled
    info = bag.bag_info(part)
    assert info["truncated"] and info["message_count"] == len(read)
    assert 0 <= info["unreadable_bytes"] < n
    if cut in (-1, -37):                         # only the footer is damaged: all messages survive
        assert len(read) == len(written)


def test_not_a_bag(tmp_path):
    p = tmp_path / "x.mcap"
    p.write_bytes(b"hello, not an mcap file")
    with pytest.raises(bag.NotABag):
        list(bag.iter_messages(p))
    with pytest.raises(FileNotFoundError):
        bag.bag_info(tmp_path / "missing.mcap")


KILLED_WRITER = textwrap.dedent("""
    import sys, numpy as np
    from handmocap.runtime import bag, codec
    w = bag.BagWriter(sys.argv[1], chunk_bytes=64 * 1024)
    i = 0
    while True:   # until SIGKILL
        data = np.full(5000, i % 256, np.uint8)
        w.write("/test/blob", "Blob", codec.encode({"header": codec.header(i), "data": data}), i + 1, i)
        i += 1
        if i == 100:
            print("ready", flush=True)
""")


def test_sigkilled_writer_leaves_a_readable_bag(tmp_path):
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(path)], stdout=subprocess.PIPE)
    try:
        assert proc.stdout.readline().strip() == b"ready"
        while path.stat().st_size < 2_000_000:
            time.sleep(0.01)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    msgs = list(bag.iter_messages(path))
    assert len(msgs) > 300                        # 2 MB of 5 kB messages, minus one open chunk
    for k, (topic, type_name, payload, log_ns) in enumerate(msgs):
        m = codec.decode(payload, type_name)
        assert (topic, m["header"]["seq"], log_ns) == ("/test/blob", k, k + 1)
        assert (m["data"] == k % 256).all()
    out = run_handbag("info", str(path), "--json")
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    assert info["truncated"] is True
    assert info["topics"]["/test/blob"]["count"] == len(msgs) > 0
    assert info["unreadable_bytes"] < 64 * 1024 + 6000   # at most the chunk being filled
    # the standard MCAP reader's default (seeking) path refuses it until it is repaired, in place
    from mcap.reader import make_reader
    with open(path, "rb") as f, pytest.raises(Exception):
        list(make_reader(f).iter_messages())
    out = run_handbag("repair", str(path))
    assert out.returncode == 0 and f"repaired: {len(msgs)} messages kept" in out.stdout, out.stdout + out.stderr
    with open(path, "rb") as f:
        standard = [(c.topic, s.name, m.data, m.log_time, m.publish_time, m.sequence)
                    for s, c, m in make_reader(f).iter_messages()]
    assert [(t, ty, p, ln) for t, ty, p, ln, _, _ in standard] == msgs            # every message, unchanged
    assert [pt for *_, pt, _ in standard] == list(range(len(msgs)))              # publish times kept
    assert not bag.bag_info(path)["truncated"]
    assert "whole already" in run_handbag("repair", str(path)).stdout


# -- handbag info / export / errors -----------------------------------------------------------
def test_info_human_and_errors(tmp_path, capsys):
    path = tmp_path / "s.mcap"
    write_sample_bag(path)
    assert handbag(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "truncated:  no" in out and "/hand/pose" in out and "HandPose" in out
    notbag = tmp_path / "n.mcap"
    notbag.write_text("nope")
    for args, needle in [(["info", str(tmp_path / "missing.mcap")], "no such bag file"),
                         (["info", str(notbag)], "not an MCAP file"),
                         (["play", str(path), "--topics", "/nope"], "no topic(s) /nope"),
                         (["export", str(path), "-o", str(tmp_path / "o.mcap")], "--foxglove")]:
        assert handbag(args) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("handbag: error: ") and needle in err[0], err


def test_export_foxglove(tmp_path):
    src, dst = tmp_path / "s.mcap", tmp_path / "fox.mcap"
    written = write_sample_bag(src)
    out = run_handbag("export", str(src), "-o", str(dst), "--foxglove")
    assert out.returncode == 0, out.stderr
    import fastjsonschema
    by_topic: dict[str, list] = {}
    with open(dst, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            body = json.loads(message.data)
            fastjsonschema.compile(json.loads(schema.data))(body)   # each message fits its schema
            by_topic.setdefault(channel.topic, []).append((schema.name, body))
    names = {t: v[0][0] for t, v in by_topic.items()}
    assert names == {"/camera/image": "foxglove.CompressedImage", "/camera/info": "foxglove.CameraCalibration",
                     "/hand/keypoints": "foxglove.ImageAnnotations", "/hand/pose": "foxglove.SceneUpdate",
                     "/test/blob": "handmocap.Blob"}
    assert all(len(v) == 5 for v in by_topic.values())

    img = by_topic["/camera/image"][0][1]
    assert img["format"] == "jpeg" and img["timestamp"] == {"sec": T0 // 10**9, "nsec": T0 % 10**9}
    jpeg = cv2.imdecode(np.frombuffer(base64.b64decode(img["data"]), np.uint8), cv2.IMREAD_COLOR)
    assert jpeg.shape == (48, 64, 3)

    cal = by_topic["/camera/info"][0][1]
    assert cal["K"] == [50, 0, 32, 0, 50, 24, 0, 0, 1] and len(cal["P"]) == 12

    ann = by_topic["/hand/keypoints"][0][1]
    kp = codec.decode(next(p for t, _, p in written if t == "/hand/keypoints"), "HandKeypoints")
    lines = [p for p in ann["points"] if p["type"] == 4]
    joints = [p for p in ann["points"] if p["type"] == 1]
    assert len(lines) == len(joints) == len(ann["texts"]) == 2
    assert len(lines[0]["points"]) == 2 * len(BONES) and len(joints[0]["points"]) == 21
    a, b = BONES[5]
    uv = kp["hands"][0]["uv"]
    assert lines[0]["points"][10] == pytest.approx({"x": uv[a, 0], "y": uv[a, 1]})
    assert lines[0]["points"][11] == pytest.approx({"x": uv[b, 0], "y": uv[b, 1]})
    assert "right" in ann["texts"][0]["text"]

    scene = by_topic["/hand/pose"][0][1]
    (entity,) = scene["entities"]
    assert entity["frame_id"] == "camera" and len(entity["spheres"]) == 21
    assert len(entity["lines"][0]["points"]) == 2 * len(BONES)

    blob = by_topic["/test/blob"][0][1]
    wire = codec.decode(blob_payload(0), "Blob")
    assert blob["data"] == wire["data"].tolist()


def test_export_foxglove_shows_hand_meshes_as_triangles(tmp_path):
    """/hand/mesh becomes a SceneUpdate of triangles with the faces of the first message that
    carries them, the messages before it too (a left hand's winding reversed)."""
    from handmocap.interop.foxglove_export import export_foxglove
    src, dst = tmp_path / "m.mcap", tmp_path / "fox.mcap"
    rng = np.random.default_rng(2)
    faces = np.array([[0, 1, 2], [1, 3, 2]], np.int32)

    def mesh(i, with_faces):
        hands = [{"track_id": 1, "handedness": "right", "vertices": rng.random((4, 3)).astype(np.float32)},
                 {"track_id": 2, "handedness": "left", "vertices": rng.random((4, 3)).astype(np.float32)}]
        body = {"header": codec.header(i, stamp_ns=T0 + i), "hands": hands}
        return codec.encode({**body, "faces": faces} if with_faces else body, "HandMesh"), hands

    with bag.BagWriter(src) as w:
        sent = [mesh(i, with_faces=(i == 1)) for i in range(3)]
        for i, (payload, _) in enumerate(sent):
            w.write("/hand/mesh", "HandMesh", payload, T0 + i, T0 + i)
    export_foxglove(src, dst)
    with open(dst, "rb") as f:
        got = [(schema.name, json.loads(m.data)) for schema, _, m in make_reader(f).iter_messages()]
    assert [name for name, _ in got] == ["foxglove.SceneUpdate"] * 3
    for (_, scene), (_, hands) in zip(got, sent):
        right, left = scene["entities"]
        assert right["id"] == "hand/1/mesh" and left["id"] == "hand/2/mesh"
        assert right["triangles"][0]["indices"] == faces.ravel().tolist()
        assert left["triangles"][0]["indices"] == faces[:, ::-1].ravel().tolist()
        assert right["triangles"][0]["points"][3] == pytest.approx(dict(zip("xyz", hands[0]["vertices"][3].tolist())),
                                                                  abs=1e-4)


# -- the recorder node and handbag play ----------------------------------------------------------
@pytest.fixture
def graph_env():
    """Environment for node subprocesses on a fresh, short run dir (unix socket paths <= 107 bytes)."""
    run = tempfile.mkdtemp(prefix="hm")
    env = {**os.environ, "HANDMOCAP_RUN_DIR": run}
    env.pop("HANDMOCAP_LAUNCH_ID", None)
    yield env
    shutil.rmtree(run, ignore_errors=True)


def wait_ready(run_dir: Path, name: str, proc: subprocess.Popen, timeout: float = 20) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        info = bus.read_node_files(run_dir).get(name)
        if info is not None and info.ready:
            return
        time.sleep(0.05)
    raise AssertionError(f"node {name} not ready after {timeout} s")


def test_play_into_recorder_is_byte_identical(tmp_path, graph_env):
    src, rec = tmp_path / "src.mcap", tmp_path / "sub" / "rec.mcap"
    written = write_sample_bag(src, extra_frames=300)   # enough that the recorder has a backlog
    recorder = subprocess.Popen([sys.executable, "-m", "handmocap.nodes.recorder", f"output:={rec}", "raw:=true"],
                                env=graph_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_ready(Path(graph_env["HANDMOCAP_RUN_DIR"]), "recorder", recorder)
        play = run_handbag("play", str(src), "--rate", "0", env=graph_env)
        assert play.returncode == 0, play.stderr
        _, err = recorder.communicate(timeout=30)   # ends by itself: its inputs ended
    finally:
        if recorder.poll() is None:
            recorder.kill()
    assert recorder.returncode == 0, err
    assert f"recorded {len(written)} message(s) to {rec}" in err
    got = [(t, ty, p) for t, ty, p, _ in bag.iter_messages(rec)]
    assert got == written
    assert not bag.bag_info(rec)["truncated"]


def test_recorder_stores_images_as_jpeg_by_default(tmp_path, graph_env):
    """Without raw:=true an image is stored as a JPEG of itself (same header, size, nearly the
    same pixels, a fraction of the bytes); every other message byte for byte."""
    src, rec = tmp_path / "src.mcap", tmp_path / "rec.mcap"
    written = write_sample_bag(src, extra_frames=20)
    recorder = subprocess.Popen([sys.executable, "-m", "handmocap.nodes.recorder", f"output:={rec}"],
                                env=graph_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_ready(Path(graph_env["HANDMOCAP_RUN_DIR"]), "recorder", recorder)
        assert run_handbag("play", str(src), "--rate", "0", env=graph_env).returncode == 0
        _, err = recorder.communicate(timeout=30)
    finally:
        if recorder.poll() is None:
            recorder.kill()
    assert recorder.returncode == 0, err
    got = [(t, ty, p) for t, ty, p, _ in bag.iter_messages(rec)]
    assert [(t, ty) for t, ty, _ in got] == [(t, ty) for t, ty, _ in written]
    images = 0
    for (topic, kind, stored), (_, _, sent) in zip(got, written):
        if kind != "Image":
            assert stored == sent, topic
            continue
        a, b = codec.decode(sent, kind), codec.decode(stored, kind)
        assert b["encoding"] == "jpeg" and len(stored) < len(sent) / 3
        assert (b["header"], b["width"], b["height"]) == (a["header"], a["width"], a["height"])
        assert np.abs(frame_bgr(b).astype(int) - frame_bgr(a)).mean() < 6
        images += 1
    assert images == 25


def test_recorder_replaces_an_earlier_bag_only_when_a_message_arrives(tmp_path, graph_env):
    """overwrite:=true keeps the earlier bag through a run that records nothing (a graph that
    failed at start) and replaces it with the messages of a run that records some."""
    src, rec = tmp_path / "src.mcap", tmp_path / "rec.mcap"
    written = write_sample_bag(src)
    rec.write_bytes(b"an earlier recording")
    run_dir = Path(graph_env["HANDMOCAP_RUN_DIR"])
    cmd = [sys.executable, "-m", "handmocap.nodes.recorder", f"output:={rec}", "overwrite:=true", "raw:=true"]
    recorder = subprocess.Popen(cmd, env=graph_env, stderr=subprocess.PIPE, text=True)
    wait_ready(run_dir, "recorder", recorder)
    recorder.send_signal(signal.SIGTERM)
    _, err = recorder.communicate(timeout=10)
    assert recorder.returncode == 0 and f"recorded nothing: {rec} left as it was" in err, err
    assert rec.read_bytes() == b"an earlier recording"
    recorder = subprocess.Popen(cmd, env=graph_env, stderr=subprocess.PIPE, text=True)
    try:
        wait_ready(run_dir, "recorder", recorder)
        assert run_handbag("play", str(src), "--rate", "0", env=graph_env).returncode == 0
        _, err = recorder.communicate(timeout=30)
    finally:
        if recorder.poll() is None:
            recorder.kill()
    assert f"recorded {len(written)} message(s) to {rec}" in err, err
    assert [(t, ty, p) for t, ty, p, _ in bag.iter_messages(rec)] == written


def test_recorder_closes_bag_on_sigterm(tmp_path, graph_env):
    rec = tmp_path / "term.mcap"
    recorder = subprocess.Popen([sys.executable, "-m", "handmocap.nodes.recorder", f"output:={rec}",
                                 "topics:=[/test/blob]"], env=graph_env, stderr=subprocess.PIPE, text=True)
    wait_ready(Path(graph_env["HANDMOCAP_RUN_DIR"]), "recorder", recorder)
    recorder.send_signal(signal.SIGTERM)
    _, err = recorder.communicate(timeout=10)
    assert recorder.returncode == 0, err
    # stopped before any message: no empty bag is left behind (a failed run used to leave one)
    assert f"recorded nothing: no {rec} written" in err and not rec.exists()


def test_recorder_refuses_to_overwrite(tmp_path, graph_env):
    rec = tmp_path / "exists.mcap"
    rec.write_bytes(b"precious")
    out = subprocess.run([sys.executable, "-m", "handmocap.nodes.recorder", f"output:={rec}"],
                         env=graph_env, capture_output=True, text=True, timeout=30)
    assert out.returncode != 0
    errors = [line for line in out.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and str(rec) in errors[0] and "already exists" in errors[0]
    assert rec.read_bytes() == b"precious"
    cli = run_handbag("record", "-o", str(rec), env=graph_env)
    assert cli.returncode == 1 and cli.stderr.strip().startswith("handbag: error: ") and str(rec) in cli.stderr
    assert rec.read_bytes() == b"precious"


def test_bagplay_node_feeds_a_launched_graph(tmp_path):
    """A bag recorded from one graph drives another through the bagplay node: payloads arrive
    unchanged and the graph drains and returns by itself."""
    from conftest import handlaunch
    first, second = tmp_path / "kp.mcap", tmp_path / "shape.mcap"
    g1 = tmp_path / "g1.yaml"
    g1.write_text(f"""
nodes:
  source: {{node: graphnodes.keypoints_source, params: {{frames: 25}}}}
  recorder: {{node: recorder, params: {{output: {first}}}}}
""")
    g2 = tmp_path / "g2.yaml"
    g2.write_text(f"""
nodes:
  bagplay: {{node: bagplay, params: {{file: {first}, rate: 0, topics: [/hand/keypoints]}}, required: true}}
  shape: {{node: shape}}
  recorder: {{node: recorder, params: {{output: {second}}}}}
""")
    for g in (g1, g2):
        r = handlaunch([g], Path(tempfile.mkdtemp(prefix="hm")))
        assert r.returncode == 0, r.stdout + r.stderr
    recorded = {t: [] for t in ("/hand/keypoints", "/hand/shape")}
    for topic, _, payload, _ in bag.iter_messages(second):
        recorded[topic].append(payload)
    original = [p for t, _, p, _ in bag.iter_messages(first) if t == "/hand/keypoints"]
    assert recorded["/hand/keypoints"] == original and len(original) == 25
    assert len(recorded["/hand/shape"]) == 25


def test_info_into_a_pipe_that_closes_early_is_no_error(tmp_path):
    """`handbag info BAG | head -1`: the reader stopped reading; that is no error of handbag's."""
    import subprocess
    path = tmp_path / "b.mcap"
    with bag.BagWriter(path) as w:
        w.write("/camera/image", "Image", image_payload(0), 1, 1)
    r = subprocess.run(["sh", "-c", f"'{sys.executable}' -m handmocap.interop.bag_cli info '{path}' | head -1"],
                       capture_output=True, text=True, timeout=60)
    assert r.stdout.startswith("path:") and "Broken pipe" not in r.stderr, r.stderr


def test_a_split_recording_survives_a_killed_recorder(tmp_path, graph_env):
    """recorder split_s:=0.5 on a 100 Hz ticker, SIGKILLed after ~2.2 s: the splits are named in
    order, every closed one reads whole with mcap's own reader (summary and footer, its count
    equal to the messages in it), and together they hold an unbroken run of the ticker's seqs."""
    rec = tmp_path / "take.mcap"
    run_dir = Path(graph_env["HANDMOCAP_RUN_DIR"])
    ticker = subprocess.Popen([sys.executable, "-m", "graphnodes.ticker", "count:=400", "hz:=100", "size:=64"],
                              env={**graph_env, "PYTHONPATH": str(Path(__file__).parent)},
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    recorder = subprocess.Popen([sys.executable, "-m", "handmocap.nodes.recorder", f"output:={rec}",
                                 "split_s:=0.5", "topics:=[/test/blob]"], env=graph_env,
                                stderr=subprocess.PIPE, text=True)
    try:
        wait_ready(run_dir, "recorder", recorder)
        time.sleep(2.2)
        recorder.kill()
        recorder.wait(timeout=10)
    finally:
        for p in (ticker, recorder):
            if p.poll() is None:
                p.kill()
    splits = bag.split_paths(rec)
    assert len(splits) >= 3 and [p.name for p in splits] == [f"take_{i:04d}.mcap" for i in range(len(splits))]
    seqs = []
    for path in splits[:-1]:                                    # closed: whole for any reader
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None and summary.statistics is not None, path
            got = [codec.decode(m.data, "Blob")["header"]["seq"] for _, _, m in reader.iter_messages()]
        assert len(got) == summary.statistics.message_count > 0
        seqs += got
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
