"""The run dir is this user's own (issue 30): made 0700, node files 0600; a squatted, open or
symlinked run dir is one clear error and nothing starts; one graph per name, atomically."""
import os
import stat
import subprocess
import sys
import time

import pytest

from conftest import graph_env, handlaunch

GRAPH = """
nodes:
  ticker: {{node: graphnodes.ticker, params: {{count: {count}, size: 64, hz: {hz}}}, required: true}}
  sink: {{node: graphnodes.sink, params: {{mode: all, out: {out}}}}}
"""


def write_graph(tmp_path, count=50, hz=100):
    p = tmp_path / "g.yaml"
    p.write_text(GRAPH.format(count=count, hz=hz, out=tmp_path / "sink.json"))
    return p


def test_made_private_and_its_node_files_too(tmp_path):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "handmocap.runtime.launch", str(write_graph(tmp_path, count=300))]
    graph = subprocess.Popen(cmd, env=graph_env(run), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while len(list(run.glob("*.json"))) < 2:
            assert time.monotonic() < deadline and graph.poll() is None
            time.sleep(0.05)
        assert stat.S_IMODE(run.stat().st_mode) == 0o700
        assert all(stat.S_IMODE(f.stat().st_mode) == 0o600 for f in run.glob("*.json"))
    finally:
        out, err = graph.communicate(timeout=60)
    assert graph.returncode == 0, out + err


@pytest.mark.parametrize("make, words", [
    (lambda d: d.mkdir(mode=0o777) or os.chmod(d, 0o777), "mode 777"),
    (lambda d: (d.parent / "elsewhere").mkdir(mode=0o700) or d.symlink_to(d.parent / "elsewhere"), "symlink"),
    (lambda d: d.mkdir(mode=0o700) or os.chown(d, 65534, 65534), "belongs to uid 65534"),
])
def test_a_squatted_or_open_run_dir_starts_nothing(tmp_path, make, words):
    if words.startswith("belongs") and os.getuid() != 0:
        pytest.skip("only root can give a folder to another user here")
    run = tmp_path / "run"
    make(run)
    r = handlaunch([write_graph(tmp_path)], run)
    assert r.returncode == 2 and words in r.stderr, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr and "started" not in r.stdout
    assert not (tmp_path / "sink.json").exists()


def test_two_launches_of_one_graph_cannot_both_start(tmp_path):
    """The second, 0.3 s after the first, is refused with one line; the first runs to its end."""
    run = tmp_path / "run"
    lf = write_graph(tmp_path, count=300, hz=100)
    cmd = [sys.executable, "-m", "handmocap.runtime.launch", str(lf)]
    first = subprocess.Popen(cmd, env=graph_env(run), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(0.3)
    second = handlaunch([lf], run)
    out, err = first.communicate(timeout=60)
    assert second.returncode == 2 and "is already running" in second.stderr, second.stdout + second.stderr
    assert first.returncode == 0, out + err
    import json
    assert json.loads((tmp_path / "sink.json").read_text())["seqs"] == list(range(300))
