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
    topic_cli.check_topic("/hand/poze")
    err = capsys.readouterr().err
    assert "no node publishes /hand/poze now (did you mean /hand/pose?)" in err and "Waiting" in err
    topic_cli.check_topic("/hand/pose")
    assert capsys.readouterr().err == ""
