"""Graph tests: real node processes started by handlaunch, talking over real ZeroMQ sockets."""
import json
import os
import signal
import subprocess
import sys
import time

from pathlib import Path

import numpy as np
import pytest

from conftest import graph_env, handlaunch


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def sink_result(path):
    return json.loads(path.read_text())


@pytest.mark.parametrize("mode", ["lossless", "all"])
def test_10000_messages_flat_out_arrive_in_order_and_none_is_lost_silently(tmp_path, run_dir, mode):
    """A source 10,000 messages flat out, faster than the sink takes them: a lossless subscriber
    gets every one in order (the source waits for it); a keep-all one (0.5 ms a message) gets
    them in order up to its bounded queue, and every message it lost is counted
    (stats["lost"], from seq gaps and the end of stream's last seq)."""
    out = tmp_path / "sink.json"
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 10000, size: 64}}, required: true}}
  sink: {{node: graphnodes.sink, params: {{mode: {mode}, out: {out}, work_s: {0.0 if mode == "lossless" else 0.0005}}}}}
""")
    r = handlaunch([lf], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    seen = sink_result(out)
    if mode == "lossless":
        assert seen["seqs"] == list(range(10000)) and seen["lost"] == 0
    else:
        seqs = np.array(seen["seqs"])
        assert seqs[0] == 0 and (np.diff(seqs) > 0).all() and seen["lost"] > 0
        # gaps and the tail after the last one received (the end of stream says the last seq)
        assert len(seqs) + seen["lost"] == 10000, (len(seqs), seen["lost"], seqs[-1])


def test_a_slow_lossless_subscriber_holds_its_publisher_and_gets_everything(tmp_path, run_dir):
    """6,000 small messages flat out to a lossless sink of 1 ms a message (6 s of work) and
    a keep-all sink of 2 ms: the lossless one gets all in order, and none waited in a queue
    longer than its bound (1,024 + 1,024 messages, ~2 s): the ticker waited for it instead of
    queueing everything (else the last would be ~6 s old). The keep-all one gets what its
    queue held, in order, and counts the rest."""
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 6000, size: 64}}, required: true}}
  lossless: {{node: graphnodes.sink, params: {{mode: lossless, work_s: 0.001, out: {tmp_path}/lossless.json}}}}
  keep_all: {{node: graphnodes.sink, params: {{mode: all, work_s: 0.002, out: {tmp_path}/all.json}}}}
""")
    r = handlaunch([lf], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    lossless, keep_all = sink_result(tmp_path / "lossless.json"), sink_result(tmp_path / "all.json")
    assert lossless["seqs"] == list(range(6000)) and lossless["lost"] == 0
    assert max(lossless["ages_ms"]) < 4000, max(lossless["ages_ms"])
    seqs = np.array(keep_all["seqs"])
    assert (np.diff(seqs) > 0).all() and len(seqs) + keep_all["lost"] == 6000 and keep_all["lost"] > 0


def test_latest_only_slow_subscriber_sees_only_fresh_frames(tmp_path, run_dir):
    """100 Hz of 640x480 BGR-sized messages to a fast and a slow (100 ms/message) latest-only
    subscriber and a keep-all one: the fast one keeps up, the slow one skips to fresh frames
    instead of building a backlog, the keep-all one loses nothing."""
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 200, size: 921600, hz: 100}}}}
  fast: {{node: graphnodes.sink, params: {{mode: latest, out: {tmp_path}/fast.json}}}}
  slow: {{node: graphnodes.sink, params: {{mode: latest, work_s: 0.1, out: {tmp_path}/slow.json}}}}
  all: {{node: graphnodes.sink, params: {{mode: all, out: {tmp_path}/all.json}}}}
""")
    r = handlaunch([lf], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    fast, slow, keep = (sink_result(tmp_path / f"{n}.json") for n in ("fast", "slow", "all"))
    assert keep["seqs"] == list(range(200))
    # generous bounds: a loaded 2-core machine must not make this flaky
    assert len(fast["seqs"]) >= 100 and np.median(fast["ages_ms"]) < 60
    # 2 s of frames at 100 ms each: about 20 frames, each fresh (a backlog would age by 90 ms a frame)
    assert 10 <= len(slow["seqs"]) <= 30
    # (the first frames can be late while the 2 cores are still busy starting 4 processes; a
    # stall of the loaded machine can make one late later on, but a backlog makes every next
    # one later still, so no two late ones follow each other)
    late = np.array(slow["ages_ms"][len(slow["ages_ms"]) // 2:]) >= 150
    assert np.median(slow["ages_ms"]) < 40 and not (late[1:] & late[:-1]).any(), slow["ages_ms"]
    assert slow["seqs"] == sorted(slow["seqs"]) and slow["seqs"][-1] == 199


def test_malformed_messages_are_dropped_and_the_node_keeps_serving(tmp_path, run_dir):
    out = tmp_path / "sink.json"
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  fuzzer: {{node: graphnodes.fuzzer, params: {{valid: 40}}}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {out}}}}}
""")
    r = handlaunch([lf], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    res = sink_result(out)
    assert res["seqs"] == list(range(40))
    # (an oversized one never gets this far between processes: zmq refuses it unread, which
    # test_drills' oversized drill shows; the codec's own size check is test_codec's)
    assert res["dropped"] == 39 * 7
    warnings = [line for line in r.stdout.splitlines() if line.startswith("[sink] WARNING dropped")]
    # one line per (topic, cause), not one per message
    causes = ["(msgpack:", "(schema:", "(array-size:", "(unknown-type:", "(2 frames, expected 3)"]
    assert len(warnings) == len(causes)
    assert all(any(c in w for w in warnings) for c in causes)
    assert "Traceback" not in r.stdout


def test_killed_node_respawns_and_a_failed_required_node_stops_the_graph(tmp_path, run_dir):
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 100000, hz: 50}}, respawn: true, respawn_delay: 0.2}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {tmp_path}/sink.json}}}}
""")
    proc = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=graph_env(run_dir),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        first = wait_for_node(run_dir, "ticker")
        wait_for_count(run_dir / "ticker.json", 20)
        os.kill(first, signal.SIGKILL)
        second = wait_for_node(run_dir, "ticker", not_pid=first)
        assert second != first
        wait_for_count(run_dir / "ticker.json", 20)
        time.sleep(0.3)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    assert "node ticker died (killed by signal 9); respawn in 0.2 s" in out
    assert "respawning ticker" in out
    seqs = sink_result(tmp_path / "sink.json")["seqs"]
    restart = [i for i in range(1, len(seqs)) if seqs[i] < seqs[i - 1]]
    assert len(restart) == 1 and seqs[restart[0]] == 0   # the new process's stream reached the sink

    lf2 = write(tmp_path, "g2.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 1000, hz: 100, fail_after: 20}}, required: true}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {tmp_path}/sink2.json}}}}
""")
    r = handlaunch([lf2], run_dir)
    assert r.returncode == 1
    assert "error: required node ticker failed (exit code 2); stopping the graph" in r.stdout
    assert "failing on purpose after 20 messages" in r.stdout

    # the same with respawn: an expected error (exit code 2) right after the start is a
    # configuration that no retry mends: the graph stops as without respawn, once
    lf3 = write(tmp_path, "g3.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 1000, hz: 100, fail_after: 20}}, required: true, respawn: true,
           respawn_delay: 0.1}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {tmp_path}/sink3.json}}}}
""")
    r = handlaunch([lf3], run_dir)
    assert r.returncode == 1 and "respawning ticker" not in r.stdout, r.stdout
    assert "error: required node ticker failed (exit code 2); stopping the graph" in r.stdout


def wait_for_node(run_dir, name, not_pid=None, timeout=20):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            info = json.loads((run_dir / f"{name}.json").read_text())
            if info["ready"] and info["pid"] != not_pid:
                return info["pid"]
        except (OSError, ValueError):
            pass
        time.sleep(0.05)
    raise AssertionError(f"node {name} did not come up")


def wait_for_count(node_file, n, timeout=10):
    """Wait until a node's status says it published n messages on /test/blob."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if json.loads(node_file.read_text())["stats"]["published"].get("/test/blob", 0) >= n:
                return
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    raise AssertionError(f"{node_file.stem} did not publish {n} messages")


def test_default_graph_listens_on_no_network_port(tmp_path, run_dir):
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 300, hz: 100}}}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {tmp_path}/sink.json}}}}
""")
    proc = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=graph_env(run_dir),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for_node(run_dir, "ticker")
        wait_for_node(run_dir, "sink")
        endpoints = [json.loads((run_dir / f"{n}.json").read_text())["endpoint"] for n in ("ticker", "sink")]
        assert all(e.startswith(f"ipc://{run_dir}/") for e in endpoints), endpoints
    finally:
        proc.communicate(timeout=30)


def free_port():
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def two_hosts(tmp_path, port, a_keys="", b_keys="", b_name="sink", a_name="a"):
    """Launch files of two graphs that cannot see each other's run dirs (as on two hosts): A's
    ticker binds tcp://127.0.0.1:PORT, B's sink connects to it; each with its `keys:` text."""
    a = write(tmp_path, f"{a_name}.yaml", f"""
{a_keys}
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 200, hz: 100}}, bind: "tcp://127.0.0.1:{port}", required: true}}
""")
    b = write(tmp_path, f"{b_name}.yaml", f"""
{b_keys}
nodes:
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {tmp_path}/{b_name}.json}}, connect: ["tcp://127.0.0.1:{port}"]}}
""")
    return a, b


def run_two_hosts(a, b_files, tmp_path):
    """Start every B graph, wait for its sink, run A to its end, stop the Bs; their outputs."""
    import tempfile
    dir_a = Path(tempfile.mkdtemp(prefix="hm"))
    bs = []
    for b in b_files:
        d = Path(tempfile.mkdtemp(prefix="hm"))
        bs.append((subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(b)], env=graph_env(d),
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True), d))
    try:
        for _, d in bs:
            wait_for_node(d, "sink")
        r = handlaunch([a], dir_a)
        time.sleep(1.0)
    finally:
        outs = []
        for proc, _ in bs:
            proc.terminate()
            outs.append(proc.communicate(timeout=30)[0])
    return r, outs


def make_keys(tmp_path, other):
    """Key pairs a, b and `other` (handkeys) in tmp_path/keys; b's public key is A's one client."""
    from handmocap.runtime.keys import main as handkeys
    keys = tmp_path / "keys"
    assert handkeys([str(keys), "a", "b", other]) == 0
    (keys / "clients").mkdir()
    (keys / "clients" / "b.key").write_bytes((keys / "b.key").read_bytes())
    return keys


def test_tcp_with_keys_reaches_the_keyed_subscriber_only(tmp_path):
    """Two "hosts" over tcp://127.0.0.1 with CURVE keys (handkeys): the subscriber with B's key
    gets every message; one with another key pair is refused (the publisher's graph logs it)
    and gets nothing; one without keys (insecure) gets nothing either."""
    keys = make_keys(tmp_path, "stranger")
    port = free_port()
    a, b = two_hosts(tmp_path, port, a_keys=f"keys: {{secret: {keys}/a.key_secret, clients: {keys}/clients}}",
                     b_keys=f"keys: {{secret: {keys}/b.key_secret, server: {keys}/a.key}}")
    _, stranger = two_hosts(tmp_path, port, b_keys=f"keys: {{secret: {keys}/stranger.key_secret, server: {keys}/a.key}}",
                            b_name="stranger", a_name="unused1")
    _, open_sink = two_hosts(tmp_path, port, b_keys="insecure: true", b_name="open", a_name="unused2")
    r, outs = run_two_hosts(a, [b, stranger, open_sink], tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    seqs = sink_result(tmp_path / "sink.json")["seqs"]
    assert len(seqs) >= 150 and seqs == sorted(seqs) and seqs[-1] == 199
    assert sink_result(tmp_path / "stranger.json")["seqs"] == []
    assert sink_result(tmp_path / "open.json")["seqs"] == []
    assert "refused a subscriber whose public key" in r.stdout, r.stdout
    assert "warning: insecure: true: tcp://127.0.0.1" in outs[2]


def test_a_forged_publisher_on_the_port_feeds_nothing(tmp_path):
    """A process that holds the port with a key pair of its own: the keyed subscriber insists on
    A's public key and takes nothing from it."""
    keys = make_keys(tmp_path, "forger")
    port = free_port()
    forged, b = two_hosts(tmp_path, port, a_keys=f"keys: {{secret: {keys}/forger.key_secret, clients: {keys}/clients}}",
                          b_keys=f"keys: {{secret: {keys}/b.key_secret, server: {keys}/a.key}}")
    r, _ = run_two_hosts(forged, [b], tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert sink_result(tmp_path / "sink.json")["seqs"] == []


def test_tcp_without_keys_is_refused_at_launch_and_a_taken_port_is_one_line(tmp_path, run_dir):
    port = free_port()
    a, _ = two_hosts(tmp_path, port)
    r = handlaunch([a], run_dir)
    assert r.returncode == 2 and "is a network endpoint without keys" in r.stderr, r.stderr
    import socket
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", port))
        holder.listen()
        a, _ = two_hosts(tmp_path, port, a_keys="insecure: true")
        r = handlaunch([a], run_dir)
    out = r.stdout + r.stderr
    assert r.returncode == 1 and f"cannot listen on tcp://127.0.0.1:{port}: the address is in use" in out, out
    assert "Traceback" not in out



def test_a_tcp_publisher_found_after_the_loop_started_is_heard(tmp_path, run_dir, monkeypatch):
    """A subscriber with keys whose loop is already running when a CURVE tcp publisher comes
    (its tcp socket is made on discovery, after the loop armed its poller) still hears it:
    the loop polls the sockets made since it started."""
    import threading

    from handmocap.runtime.keys import ENV, Keys
    from handmocap.runtime.node import Node
    keys = make_keys(tmp_path, "unused")
    monkeypatch.setenv(ENV, Keys(secret=f"{keys}/b.key_secret", server=f"{keys}/a.key").to_env())
    sub = Node("late_sub", argv=[])
    sub.subscribe("/tick", "Blob", mode="all")
    got = []
    loop = threading.Thread(target=lambda: got.extend(m.data["header"]["seq"] for m in sub.events()))
    loop.start()
    time.sleep(0.3)                       # the loop is armed, with no publisher yet
    monkeypatch.setenv(ENV, Keys(secret=f"{keys}/a.key_secret", clients=f"{keys}/clients").to_env())
    monkeypatch.setenv("HANDMOCAP_BIND", f"tcp://127.0.0.1:{free_port()}")
    pub = Node("late_pub", argv=[])
    pub.advertise("/tick", "Blob")
    try:
        assert not pub.wait_for_subscribers(10.0), "the subscriber never connected"
        for i in range(20):
            pub.publish("/tick", {"data": np.full(8, i, np.uint8)})
    finally:
        pub.close()
        loop.join(10.0)
        sub.close()
    assert not loop.is_alive(), "the subscriber never heard the end of stream"
    assert got == list(range(20))

def test_one_node_with_latest_and_keep_all_inputs_small_and_large(run_dir):
    """In one process: a node that subscribes to one topic keep-all and another latest-only
    (two sockets, polled) gets every small message in order and the freshest large one, with
    the wire bytes unchanged (large payloads are received into zmq frames without a copy)."""
    from handmocap.runtime import codec
    from handmocap.runtime.node import Node
    pub = Node("pub", argv=[])
    pub.advertise("/small", "Blob")
    pub.advertise("/big", "Blob")
    sub = Node("sub", argv=[])
    sub.subscribe("/small", "Blob", mode="all")
    sub.subscribe("/big", "Blob", mode="latest")
    sub.ready()
    assert not pub.wait_for_subscribers(10.0)
    big = np.arange(1_000_000, dtype=np.uint8)
    for i in range(20):   # fewer than the bus queues hold: none lost while nothing reads them
        pub.publish("/small", {"data": np.full(8, i, np.uint8)})
        pub.publish("/big", {"data": big})
    pub.close()
    small, bigs = [], []
    for msg in sub.events():
        if msg.topic == "/small":
            small.append(int(msg.data["data"][0]))
            assert codec.decode(msg.raw, "Blob")["header"]["seq"] == msg.data["header"]["seq"]
        else:
            bigs.append(msg.data["header"]["seq"])
            np.testing.assert_array_equal(msg.data["data"], big)
            assert len(msg.raw) > 1_000_000 and isinstance(msg.raw, bytes)
    sub.close()
    assert small == list(range(20))   # keep-all: every one, in order; the loop ended on end-of-stream
    assert bigs and bigs == sorted(bigs) and bigs[-1] == 19


def test_a_forged_end_of_stream_is_ignored_and_counted(tmp_path, run_dir):
    """A node of the graph sends end-of-stream marks on /test/blob that name the ticker (no
    token, a wrong one), on the data path and the control channel: the sink ignores them,
    counts them, and still gets all 300 messages."""
    out = tmp_path / "sink.json"
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 300, size: 64, hz: 200}}, required: true}}
  eos_forger: {{node: graphnodes.eos_forger}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {out}}}}}
""")
    r = handlaunch([lf], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    res = sink_result(out)
    # the two on the data path always arrive (the forger waits for its subscribers); the two
    # on the control channel only if the sink's control socket had connected by then
    assert res["seqs"] == list(range(300)) and 2 <= res["dropped"] <= 4
    assert sum("[sink] WARNING dropped an end of stream on /test/blob" in line for line in r.stdout.splitlines()) == 1


def test_a_node_that_ends_before_its_inputs_is_reported(tmp_path, run_dir):
    """A sink that stops by itself (max_messages) while the ticker still publishes: handlaunch
    says so and exits 1 instead of a silent 0."""
    out = tmp_path / "sink.json"
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 300, size: 64, hz: 100}}}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {out}, max_messages: 10}}}}
""")
    r = handlaunch([lf], run_dir)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "error: sink ended while ticker, which publish its input /test/blob, still run" in r.stdout


def test_a_required_node_that_ends_before_its_inputs_stops_the_graph(tmp_path, run_dir):
    """The same sink, required (a recorder, say): the graph does not run on without it; it
    stops at once, exit 1, naming the node (the ticker would publish for 30 s)."""
    out = tmp_path / "sink.json"
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 3000, size: 64, hz: 100}}}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {out}, max_messages: 10}}, required: true}}
""")
    t0 = time.monotonic()
    r = handlaunch([lf], run_dir)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "error: required node sink ended before its inputs did; stopping the graph" in r.stdout, r.stdout
    assert time.monotonic() - t0 < 20


def test_a_graph_ends_when_its_nodes_have_ended_even_if_one_failed(tmp_path, run_dir):
    """A node that is not required fails: it is reported and the rest of the graph runs to its
    end; handlaunch then returns (it used to wait for ever for that node's exit code 0)."""
    out = tmp_path / "sink.json"
    lf = write(tmp_path, "g.yaml", f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 50, hz: 100}}, required: true}}
  flaky: {{node: graphnodes.ticker, params: {{topic: /other, count: 50, fail_after: 3}}}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {out}}}}}
""")
    r = handlaunch([lf], run_dir, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "warning: node flaky failed" in r.stdout and "all nodes finished" in r.stdout
    assert sink_result(out)["seqs"] == list(range(50))
