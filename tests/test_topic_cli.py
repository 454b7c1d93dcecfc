"""handtopic against a live graph."""
import subprocess
import sys
import time

from conftest import graph_env


def test_list_echo_hz_delay_on_a_live_graph(tmp_path, run_dir):
    lf = tmp_path / "g.yaml"
    lf.write_text(f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 600, hz: 100}}}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {tmp_path}/sink.json}}}}
""")
    env = graph_env(run_dir)
    graph = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        def handtopic(*args):
            return subprocess.run([sys.executable, "-m", "handmocap.runtime.topic_cli", *args], env=env,
                                  capture_output=True, text=True, timeout=30).stdout

        deadline = time.monotonic() + 20
        while "/test/blob" not in handtopic("list") and time.monotonic() < deadline:
            time.sleep(0.1)
        assert handtopic("list", "-v").strip() == "/test/blob [Blob]  pub: ticker  sub: sink"
        assert "ticker" in handtopic("nodes") and "alive" in handtopic("nodes")
        echo = handtopic("echo", "/test/blob", "-n", "2")
        assert echo.count("---") == 2 and "stamp_ns:" in echo and "seq:" in echo
        hz = handtopic("hz", "/test/blob", "--duration", "2.2")
        rate = float(hz.split("average rate:")[-1].split()[0])
        assert 60 < rate < 140   # 100 Hz, generous for a busy machine
        delay = handtopic("delay", "/test/blob", "--duration", "1.2")
        assert "delay p50:" in delay and "p95:" in delay
    finally:
        graph.terminate()
        graph.communicate(timeout=20)


def test_no_graph_and_unknown_topics_are_said_not_silent(tmp_path, monkeypatch, capsys):
    """list / nodes without a graph: one line and exit 1 (they used to print nothing); echo of a
    topic nobody publishes: a line naming the close ones, then it waits (it used to wait mutely)."""
    from handmocap.runtime import topic_cli
    monkeypatch.setenv("HANDMOCAP_RUN_DIR", str(tmp_path / "empty"))
    for cmd in ("list", "nodes"):
        assert topic_cli.main([cmd]) == 1
        assert "no graph is running in" in capsys.readouterr().err
    from handmocap.runtime.bus import NodeInfo, write_node_file, run_dir
    import os
    write_node_file(run_dir(), NodeInfo("ik", os.getpid(), "ipc:///nowhere", {"/hand/pose": "HandPose"}))
    assert not topic_cli.check_topic("/hand/poze", wait=True)
    err = capsys.readouterr().err
    assert "no node publishes /hand/poze now (did you mean /hand/pose?)" in err and "Waiting" in err
    assert topic_cli.check_topic("/hand/pose")
    assert capsys.readouterr().err == ""
    # without --wait, echo / hz / delay of a topic nobody publishes stop at once (they waited for ever)
    for cmd in ("echo", "hz", "delay"):
        assert topic_cli.main([cmd, "/hand/poze"]) == 1
        assert "did you mean /hand/pose?" in capsys.readouterr().err


def test_hz_says_when_the_stream_stopped_and_nodes_forgets_stopped_tools(tmp_path, run_dir):
    """hz on a stream that ends: the last reports say "no new messages" (they repeated the last
    rate for ever); `nodes` afterwards lists no stopped handtopic."""
    lf = tmp_path / "g.yaml"
    lf.write_text(f"""
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: 150, hz: 100}}}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {tmp_path}/sink.json}}}}
  idle: {{node: graphnodes.ticker, params: {{topic: /idle, count: 1000000, hz: 1}}}}
""")
    env = graph_env(run_dir)
    graph = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    handtopic = lambda *args: subprocess.run([sys.executable, "-m", "handmocap.runtime.topic_cli", *args], env=env,
                                             capture_output=True, text=True, timeout=30).stdout
    try:
        hz = handtopic("hz", "/test/blob", "--wait", "--duration", "5").strip().splitlines()
        assert any(line.startswith("average rate:") for line in hz), hz
        assert hz[-1] == "no new messages", hz
        assert "_handtopic_" not in handtopic("nodes")
    finally:
        graph.terminate()
        graph.communicate(timeout=20)
