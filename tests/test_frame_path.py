"""The frame's path: a large Image decodes without copying its pixels (codec fast path), and
malformed frames are still rejected with the same reasons as by a full unpack."""
import threading

import msgpack
import numpy as np
import pytest

from handmocap.runtime import codec
from handmocap.runtime.frames import image_message


def frame_payload(extra=None, view=False):
    f = np.random.default_rng(1).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    msg = {"header": codec.header(3, "camera", 123), **(extra or {}), **image_message(f)}
    return f, (codec.encode_view(msg) if view else codec.encode(msg))


def slow_decode(payload, type_name):
    """The full unpack (msgpack copies the pixels): what the fast path must agree with."""
    old = codec._TAIL_MIN
    codec._TAIL_MIN = 1 << 62
    try:
        return codec.decode(payload, type_name)
    finally:
        codec._TAIL_MIN = old


def image_subscriber(name, subscribed, on_message):
    """A node thread `name` in this process: keep-all /camera/image, `subscribed` set once it
    listens, on_message(msg) for each image until the node closes."""
    from handmocap.runtime import node as nm
    nm._local.settings = {"HANDMOCAP_NODE_NAME": name}
    with nm.Node(name) as n:
        n.subscribe("/camera/image", "Image", mode="all")
        subscribed.set()
        for m in n:
            on_message(m)


def run_threads(targets, timeout):
    """Run the functions in threads of their own and wait for them (each at most `timeout` s)."""
    threads = [threading.Thread(target=f) for f in targets]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout)


@pytest.mark.parametrize("view", [False, True])
def test_a_frame_decodes_as_a_read_only_view_of_the_payload(view):
    f, payload = frame_payload(view=view)
    out = codec.decode(payload, "Image")
    np.testing.assert_array_equal(out["data"], f)
    assert not out["data"].flags.writeable
    # no copy: the pixels are the payload's own bytes
    assert np.shares_memory(out["data"], np.frombuffer(payload, np.uint8))
    ref = slow_decode(payload, "Image")
    assert {k: v for k, v in out.items() if k != "data"} == {k: v for k, v in ref.items() if k != "data"}
    assert not np.shares_memory(ref["data"], np.frombuffer(payload, np.uint8))


def test_a_truncated_frame_is_rejected_as_by_a_full_unpack():
    _, payload = frame_payload()
    for cut in (payload[:-1], payload[:-100_000], payload[:len(payload) // 2]):
        with pytest.raises(codec.MalformedMessage) as e:
            codec.decode(cut, "Image")
        with pytest.raises(codec.MalformedMessage) as ref:
            slow_decode(cut, "Image")
        assert e.value.reason == ref.value.reason == "msgpack", (e.value, ref.value)


def test_pixels_that_do_not_fit_the_shape_are_rejected():
    raw = msgpack.unpackb(frame_payload()[1])
    raw["data"]["data"] = raw["data"]["data"][:-3]   # a whole message, 3 bytes short of (480,640,3)
    payload = msgpack.packb(raw, use_bin_type=True)
    assert len(payload) > codec._TAIL_MIN
    with pytest.raises(codec.MalformedMessage) as e:
        codec.decode(payload, "Image")
    assert e.value.reason == "array-size" and "needs 921600 bytes, got 921597" in str(e.value)
    raw["data"]["data"] += b"\0" * 3
    raw["data"]["shape"] = [480, 640, "3"]
    with pytest.raises(codec.MalformedMessage) as e:
        codec.decode(msgpack.packb(raw, use_bin_type=True), "Image")
    assert e.value.reason == "schema"


def test_a_decoy_bin32_header_before_the_pixels_changes_nothing():
    """A 0xc6 byte with the right length after it inside an earlier field: the fast path must
    not split there (it falls back to the full unpack, or finds the real header)."""
    f, payload = frame_payload({"note": b"\xc6\0\0\0\0"})
    i = payload.index(b"\xc6\0\0\0\0")
    payload = payload[:i + 1] + (len(payload) - i - 5).to_bytes(4, "big") + payload[i + 5:]
    assert codec._tail_start(payload) == i   # the decoy is the first candidate
    out = codec.decode(payload, "Image")
    np.testing.assert_array_equal(out["data"], f)
    assert "note" not in out   # undeclared: dropped on receipt


def test_a_frame_whose_pixels_are_not_last_decodes_as_before():
    """Only a payload whose last item is the long binary takes the fast path; a frame with a
    field after its pixels (an undeclared one here, dropped on receipt) is unpacked whole, as before."""
    f = np.random.default_rng(2).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    payload = codec.encode({"header": codec.header(1), **image_message(f), "note": "after the pixels"})
    assert len(payload) > codec._TAIL_MIN and codec._tail_start(payload) == -1
    out = codec.decode(payload, "Image")
    np.testing.assert_array_equal(out["data"], f)
    assert "note" not in out
    assert not np.shares_memory(out["data"], np.frombuffer(payload, np.uint8))


def test_in_a_container_the_detector_reads_the_sources_own_buffer(run_dir, monkeypatch):
    """Two nodes as threads of one container (shared zmq Context, inproc://): the receiver's
    pixels are the publisher's pooled payload buffer itself, past the message's small head:
    no copy on the way (zero-copy send, inproc passes the message, decode views it)."""
    import time
    import uuid

    import zmq

    from handmocap.runtime import node as nm
    ctx = zmq.Context()
    monkeypatch.setitem(nm._SHARED, "ctx", ctx)
    monkeypatch.setitem(nm._SHARED, "token", uuid.uuid4().hex)
    sent, got = {}, []
    encode_view = codec.encode_view

    def spy(msg, type_name=None):
        view = encode_view(msg, type_name)
        sent[msg["header"]["seq"]] = (np.frombuffer(view, np.uint8).ctypes.data, len(view))
        return view
    monkeypatch.setattr(codec, "encode_view", spy)
    subscribed = threading.Event()

    def source():
        nm._local.settings = {"HANDMOCAP_NODE_NAME": "src"}
        with nm.Node("src") as n:
            n.advertise("/camera/image", "Image")
            subscribed.wait(10)
            deadline = time.monotonic() + 10
            while n.pub.subscriber_count("/camera/image") < 1 and time.monotonic() < deadline:
                time.sleep(0.01)
            f = np.arange(480 * 640 * 3, dtype=np.uint32).astype(np.uint8).reshape(480, 640, 3)
            for _ in range(6):
                n.publish("/camera/image", image_message(f))
                time.sleep(0.02)

    def detector():
        image_subscriber("det", subscribed, lambda m: got.append(
            (m.data["header"]["seq"], m.data["data"].ctypes.data, m.data["data"][479, 639, 2])))

    run_threads([detector, source], timeout=30)
    ctx.term()
    assert [s for s, _, _ in got] == list(range(6))
    assert all(px == (480 * 640 * 3 - 1) % 256 for _, _, px in got)
    # the first message on a socket is received as bytes (its size is not known yet), the rest in place
    offsets = {addr - sent[seq][0] for seq, addr, _ in got[1:]}
    assert len(offsets) == 1 and 0 < offsets.pop() < 200, got


def test_replay_decodes_just_in_time_and_keeps_the_frame_rate(tmp_path, monkeypatch):
    """At rate 1, replay decodes each frame shortly before it is due (not while the graph still
    works on the previous one) and still sends every frame on the source's clock."""
    from conftest import DEMO_CLIP
    from source_nodes import run_source
    r = run_source("handmocap.nodes.replay", {"source": str(DEMO_CLIP), "rate": 1.0})
    assert r.returncode == 0, r.stderr
    stamps = np.array([m["header"]["stamp_ns"] for m in r.messages["/camera/image"]]) / 1e9
    assert len(stamps) == 90
    late = (stamps - stamps[0]) - np.arange(90) / 30.0   # behind the 30 fps schedule, s
    assert np.median(np.diff(stamps)) == pytest.approx(1 / 30, abs=0.002)
    assert np.percentile(late, 50) < 0.005 and late.max() < 0.25, late



def test_a_large_payload_is_in_flight_until_every_receiver_lets_go():
    """Publisher.in_flight counts zero-copy payloads that zmq or a receiver in this process
    still holds; wait_in_flight blocks until fewer than the limit are."""
    import time

    import zmq

    from handmocap.runtime import bus
    ctx = zmq.Context()
    pub = bus.Publisher(ctx, "inproc://flight")
    sub = ctx.socket(zmq.SUB)
    sub.connect("inproc://flight")
    sub.subscribe(bus.topic_frame("/camera/image"))
    deadline = time.monotonic() + 5
    while pub.subscriber_count("/camera/image") < 1 and time.monotonic() < deadline:
        time.sleep(0.005)
    _, payload = frame_payload(view=True)
    for _ in range(3):
        pub.send("/camera/image", "Image", payload)
    pub.send("/camera/info", "CameraInfo", b"small")   # copied: never in flight
    held = [sub.recv_multipart(copy=False) for _ in range(3)]
    assert pub.in_flight == 3 and not pub.wait_in_flight(3, 0.05)
    del held[0]
    assert pub.wait_in_flight(3, 5.0)
    held.clear()
    assert pub.wait_in_flight(1, 5.0) and pub.in_flight == 0
    sub.close()
    pub.close()
    ctx.term()


def test_replay_at_rate_0_runs_only_a_few_frames_ahead_of_a_slow_subscriber(run_dir, monkeypatch):
    """At rate 0 ("as fast as the graph takes them") replay does not decode the whole video
    into a keep-all queue: a slow keep-all subscriber in its container holds it back, so each
    frame waits there a few frames' time at most (and every frame arrives)."""
    import time
    import uuid

    import zmq

    from conftest import DEMO_CLIP
    from handmocap.runtime import node as nm
    from handmocap.nodes import replay
    ctx = zmq.Context()
    monkeypatch.setitem(nm._SHARED, "ctx", ctx)
    monkeypatch.setitem(nm._SHARED, "token", uuid.uuid4().hex)
    waited, subscribed = [], threading.Event()

    def source():
        subscribed.wait(10)
        nm._local.settings = {"HANDMOCAP_NODE_NAME": "replay",
                              "HANDMOCAP_PARAMS": f'{{"source": "{DEMO_CLIP}", "rate": 0, "start": 2.3}}'}
        n = nm.Node("replay", params=replay.PARAMS)
        n.advertise("/camera/image", "Image")   # (replay does it too) so that the subscriber connects first
        deadline = time.monotonic() + 10
        while n.pub.subscriber_count("/camera/image") < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        try:
            replay.replay(n)
        finally:
            n.close()

    def slow():
        def on_image(m):
            waited.append((m.recv_ns - m.stamp_ns) / 1e9)
            time.sleep(0.05)
        image_subscriber("slow", subscribed, on_image)

    run_threads([slow, source], timeout=60)
    ctx.term()
    assert len(waited) == 21, len(waited)
    # without the bound, frame i would wait ~i * 50 ms (a whole video's backlog)
    assert max(waited) < (replay.AHEAD + 2) * 0.05, waited
