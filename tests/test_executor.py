"""handmocap.runtime.executor: several nodes of a container called in turn by one thread."""
import threading
import time
import uuid

import numpy as np
import pytest
import zmq

from handmocap.runtime import executor
from handmocap.runtime import node as nm


@pytest.fixture
def container(run_dir, monkeypatch):
    """This process as a container: one zmq Context, inproc:// between its nodes."""
    ctx = zmq.Context()
    monkeypatch.setitem(nm._SHARED, "ctx", ctx)
    monkeypatch.setitem(nm._SHARED, "token", uuid.uuid4().hex)
    yield ctx
    nm._local.__dict__.pop("settings", None)   # this thread's launch settings (make_node): not for later tests
    ctx.term()


def make_node(name, sub=None, pub=None):
    nm._local.settings = {"HANDMOCAP_NODE_NAME": name}
    n = nm.Node(name)
    if sub:
        n.subscribe(sub, "Blob", mode="all")
    if pub:
        n.advertise(pub, "Blob")
    return n


def text(s):
    return {"data": np.frombuffer(s.encode(), np.uint8)}


def read(msg):
    return bytes(msg.data["data"]).decode()


def source(n_messages, started, every_s=0.0):
    """A source thread: waits for its subscriber, sends n_messages on /a (one every `every_s`),
    closes (end of stream)."""
    with make_node("src", pub="/a") as src:
        started.wait(10)
        deadline = time.monotonic() + 10
        while src.pub.subscriber_count("/a") < 1 and time.monotonic() < deadline:
            time.sleep(0.005)
        for i in range(n_messages):
            src.publish("/a", text(str(i)))
            time.sleep(every_s)


def chain(fail_at=None):
    """Nodes A (/a -> /b) and B (/b): their handlers log (node, thread, text); A raises at fail_at."""
    calls = []
    a, b = make_node("A", sub="/a", pub="/b"), make_node("B", sub="/b")

    def on_a(msg):
        calls.append(("A", threading.get_ident(), read(msg)))
        if read(msg) == fail_at:
            raise ValueError("bad message")
        a.publish("/b", text(read(msg)), stamp_ns=msg.stamp_ns)

    def on_b(msg):
        calls.append(("B", threading.get_ident(), read(msg)))
    return [({"name": "A"}, a, on_a), ({"name": "B"}, b, on_b)], calls


def spin_in_thread(exits, **kw):
    """Set up A and B and spin them in a thread of their own (as a container's executor
    thread: nodes close in the thread that made them); returns (thread, calls)."""
    out = {}

    def run():
        out["nodes"], out["calls"] = chain(**kw)
        executor.spin(out["nodes"], lambda m, code: exits.append((m["name"], code)))
    t = threading.Thread(target=run)
    t.start()
    deadline = time.monotonic() + 10
    while "calls" not in out and time.monotonic() < deadline:
        time.sleep(0.005)
    return t, out["calls"]


def run_chain(n_messages, every_s=0.0, **kw):
    """A source thread sends n_messages through A and B spun in a thread; returns (spinner
    thread, exits, calls) once both ended (or 30 s passed)."""
    exits, started = [], threading.Event()
    spinner, calls = spin_in_thread(exits, **kw)
    src = threading.Thread(target=source, args=(n_messages, started, every_s))
    src.start()
    started.set()
    spinner.join(30)
    src.join(10)
    return spinner, exits, calls


def test_nodes_are_called_in_turn_on_one_thread_and_end_in_order(container):
    spinner, exits, calls = run_chain(50, 0.002)
    assert not spinner.is_alive(), "the executor did not end when its inputs ended"
    assert exits == [("A", 0), ("B", 0)]            # A ends first, B once it heard A's end of stream
    assert [c[2] for c in calls if c[0] == "A"] == [str(i) for i in range(50)]
    assert [c[2] for c in calls if c[0] == "B"] == [str(i) for i in range(50)]
    assert {c[1] for c in calls} == {spinner.ident}


def test_a_handler_that_raises_loses_that_message_only(container, caplog):
    """One bad message must not stop a node (issue 30): A's handler raises on "3"; that message
    is dropped, counted and logged, and A and B go on with the rest and end normally."""
    spinner, exits, calls = run_chain(10, fail_at="3")
    assert not spinner.is_alive()
    assert exits == [("A", 0), ("B", 0)]
    assert [c[2] for c in calls if c[0] == "B"] == [str(i) for i in range(10) if i != 3]
    assert any("bad message" in r.getMessage() and r.levelname == "WARNING" for r in caplog.records)


def test_a_node_that_fails_to_start_is_closed_and_reported(container, tmp_path, monkeypatch):
    mod = tmp_path / "failing_node.py"
    mod.write_text("from handmocap.runtime.node import Node\n"
                   "def start():\n"
                   "    node = Node('failing')\n"
                   "    node.advertise('/x', 'Blob')\n"
                   "    raise FileNotFoundError('model nope.onnx not found')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    exits = []
    started = executor.start_nodes([{"name": "failing", "module": "failing_node", "settings": {}}],
                                   lambda m, code: exits.append((m["name"], code)))
    assert started == [] and exits == [("failing", 2)]
    assert not [n for n in nm._OPEN_NODES if n.name == "failing"]
    assert executor.can_run_in_turn("nodes.detector") and not executor.can_run_in_turn("nodes.replay")


def test_a_turn_takes_what_was_queued_when_it_began(container):
    """Node.steps(): a turn yields the messages queued when it began, then IDLE, however
    many arrive meanwhile (a source that always has the next frame ready can't keep the
    nodes after this one waiting)."""
    src, sink = make_node("src", pub="/a"), make_node("sink", sub="/a")
    steps = sink.steps()
    assert next(steps) is nm.IDLE    # nothing yet (the first turn also connects to src)
    deadline = time.monotonic() + 10
    while src.pub.subscriber_count("/a") < 1 and time.monotonic() < deadline:
        time.sleep(0.005)
    for i in range(3):
        src.publish("/a", text(str(i)))
    time.sleep(0.1)
    got = [read(next(steps))]
    for i in range(3, 8):               # arrive during the turn
        src.publish("/a", text(str(i)))
    time.sleep(0.1)
    while (msg := next(steps)) is not nm.IDLE:
        got.append(read(msg))
    assert got == ["0", "1", "2"]
    while (msg := next(steps)) is not nm.IDLE:
        got.append(read(msg))
    assert got == [str(i) for i in range(8)]
    steps.close()
    sink.close()
    src.close()


def test_messages_between_nodes_of_a_container_skip_the_checks_and_arrive_the_same(container, monkeypatch):
    """Inside a container every message was encoded by this process's own code: it arrives over
    inproc:// and is decoded without the schema, NaN and stamp checks (codec.decode_trusted),
    as the same message a checked decode gives. A message from another process is still checked
    (every other test of the bus; here: what codec.decode is called for)."""
    from handmocap.runtime import codec
    kinds = []
    monkeypatch.setattr(codec, "decode", lambda p, t, *a, _d=codec.decode: kinds.append("checked") or _d(p, t, *a))
    monkeypatch.setattr(codec, "decode_trusted",
                        lambda p, t, _d=codec.decode_trusted: kinds.append("trusted") or _d(p, t))
    spinner, exits, calls = run_chain(20, 0.002)
    assert exits == [("A", 0), ("B", 0)]
    assert [c[2] for c in calls if c[0] == "B"] == [str(i) for i in range(20)]
    # the first message of a type is checked (decode_trusted learns the type's converter from it)
    assert kinds.count("trusted") >= 38 and kinds.count("checked") <= 2, kinds


@pytest.mark.parametrize("size", [100, 640 * 480 * 3])
def test_a_trusted_decode_gives_what_the_checked_one_does(size):
    from handmocap.runtime import codec
    data = np.arange(size, dtype=np.uint32).astype(np.uint8)
    payload = codec.encode({"header": codec.header(3), "data": data})
    codec.decode(payload, "Blob")   # (the type's converter, as a node's first message makes it)
    checked, trusted = codec.decode(payload, "Blob"), codec.decode_trusted(payload, "Blob")
    assert checked["header"] == trusted["header"]
    np.testing.assert_array_equal(checked["data"], trusted["data"])
    assert not trusted["data"].flags.writeable
    with pytest.raises(codec.MalformedMessage):
        codec.decode_trusted(b"\xc1 not msgpack", "Blob")


def test_a_step_leaves_discovery_scans_to_the_executor(container, monkeypatch):
    """A scan reads every node file (0.3-1 ms): a step must not run one, or it lands on the
    message that woke the executor; the executor calls Node.scan when nothing is queued."""
    sink = make_node("sink", sub="/a")
    steps = sink.steps()
    assert next(steps) is nm.IDLE
    looked = []
    monkeypatch.setattr(sink, "_scan", lambda force=False, _scan=sink._scan: looked.append(force) or _scan(force))
    src = make_node("src", pub="/a")            # a publisher that comes later: found by a scan
    sink._next_scan = 0.0                       # a scan is due
    for _ in range(3):
        assert next(steps) is nm.IDLE
    assert looked == [] and sink.scan_due()
    sink.scan()                                 # the executor's, when it is about to wait
    assert looked == [False] and not sink.scan_due() and not sink.scan_overdue()
    deadline = time.monotonic() + 10
    while src.pub.subscriber_count("/a") < 1 and time.monotonic() < deadline:
        time.sleep(0.005)
    src.publish("/a", text("found"))
    time.sleep(0.1)
    assert read(next(steps)) == "found"
    steps.close()
    sink.close()
    src.close()


def test_an_idle_executor_beats_for_its_nodes_and_their_threads_leave_it(container, monkeypatch):
    """A heartbeat (the node file rewritten, 0.3-0.6 ms) from a node's own thread lands at any
    moment, maybe on a frame; the executor writes it when it has nothing to do (Node.beat), and
    the thread writes only when nobody did for 0.9 x HEARTBEAT_S (a handler that runs long)."""
    from handmocap.runtime import bus
    writers = []
    monkeypatch.setattr(bus, "write_node_file",
                        lambda d, info, _w=bus.write_node_file: writers.append(threading.get_ident()) or _w(d, info))
    n = make_node("beater", sub="/a")
    assert not n.beat_due()                     # written when it subscribed
    writers.clear()
    me = threading.get_ident()
    deadline = time.monotonic() + 3 * bus.HEARTBEAT_S
    while time.monotonic() < deadline:          # an executor's idle moments
        n.beat()
        time.sleep(0.02)
    assert writers.count(me) >= 3 and len(writers) - writers.count(me) <= 1, writers
    writers.clear()
    time.sleep(3 * bus.HEARTBEAT_S)             # no executor beats: the node's own thread does
    assert len(writers) >= 2 and me not in writers
    n.close()
