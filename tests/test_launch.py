"""Launch files are checked completely before any process starts; errors name file and line."""
import subprocess
import sys

import pytest
from pathlib import Path

from conftest import ROOT
from handmocap.runtime.launch import LaunchError, load_launch_file

GOOD = """\
args:
  input: {help: a video}
  rate: {default: 1.0}
nodes:
  replay:
    node: replay
    params: {source: $(var input), rate: $(var rate)}
    required: true
  recorder:
    node: recorder
    params: {output: out-$(var rate).mcap}
"""


@pytest.fixture(autouse=True)
def in_tmp_with_sources(tmp_path, monkeypatch):
    """Relative paths resolve in tmp_path, where the sources the files name exist (the replay
    node's check_params wants its source to exist)."""
    monkeypatch.chdir(tmp_path)
    for name in ("x", "clip.mp4", "kept.mcap"):
        (tmp_path / name).write_bytes(b"")


def write(tmp_path, text):
    p = tmp_path / "g.yaml"
    p.write_text(text)
    return p


def test_good_file_substitutes_arguments_keeping_types(tmp_path):
    lf = load_launch_file(write(tmp_path, GOOD), {"input": "clip.mp4", "rate": 2})
    replay, recorder = lf.nodes
    assert replay.module == "handmocap.nodes.replay" and replay.required
    assert replay.params == {"source": "clip.mp4", "rate": 2}
    assert recorder.params == {"output": "out-2.mcap"}


@pytest.mark.parametrize("text, args, line, words", [
    (GOOD, {}, 2, "argument 'input' is required"),
    (GOOD, {"input": "x", "speed": 3}, 1, "unknown argument 'speed'"),
    (GOOD.replace("node: recorder", "node: recorderz"), {"input": "x"}, 10, "unknown node type 'recorderz'"),
    (GOOD.replace("required: true", "requird: true"), {"input": "x"}, 8, "unknown key 'requird'"),
    (GOOD.replace("$(var rate)}", "$(var speed)}"), {"input": "x"}, 7, "$(var speed) is not declared"),
    (GOOD.replace("rate: $(var rate)}", "rat: 1}"), {"input": "x"}, 7, "has no parameter 'rat'"),
    (GOOD.replace("  replay:\n", "  replay:\n   - [\n"), {"input": "x"}, 8, "malformed YAML"),
    (GOOD + "  detector:\n    node: detector\n    params: {handedness: rigth}\n", {"input": "x"}, 14,
     "detector param handedness: expected left, right or null, got 'rigth'"),
    (GOOD + "  detector:\n    node: detector\n    params: {max_hands: two}\n", {"input": "x"}, 14,
     "detector param max_hands: expected a number or null"),
    (GOOD + "  detector:\n    node: detector\n    params: {detnet: models/nothere.onnx}\n", {"input": "x"}, 14,
     "detector param detnet: no such file models/nothere.onnx"),
    (GOOD + "  ik:\n    node: ik\n    params: {iknet: int8, model: MANO_RIGHT.pkl}\n", {"input": "x"}, 14,
     "ik param model: no such file MANO_RIGHT.pkl"),
    (GOOD + "  ik:\n    node: ik\n    params: {smooth: maybe}\n", {"input": "x"}, 14,
     "ik param smooth: expected true or false, got 'maybe'"),
    (GOOD + "  ik:\n    node: ik\n    params: {rot_min_cutoff: 0}\n", {"input": "x"}, 14,
     "ik param rot_min_cutoff: expected a number > 0, got 0"),
    (GOOD + "  shape:\n    node: shape\n    params: {window: 0.5}\n", {"input": "x"}, 14,
     "shape param window: expected an integer >= 1, got 0.5"),
    (GOOD + "  camera:\n    node: camera\n    params: {fps: thirty}\n", {"input": "x"}, 14,
     "camera param fps: expected a number > 0, got 'thirty'"),
    (GOOD + "  camera:\n    node: camera\n    params: {calibration: nocalib.yaml}\n", {"input": "x"}, 14,
     "camera param calibration: calibration file nocalib.yaml"),
    (GOOD + "  viz:\n    node: visualizer\n    params: {mesh: yes please}\n", {"input": "x"}, 14,
     "visualizer param mesh: expected true or false, got 'yes please'"),
    (GOOD + "  bridge:\n    node: bridge\n    params: {port: 87.65}\n", {"input": "x"}, 14,
     "bridge param port: expected an integer >= 0, got 87.65"),
    (GOOD + "  play:\n    node: bagplay\n    params: {file: gone.mcap}\n", {"input": "x"}, 14,
     "bagplay param file: no such bag gone.mcap"),
    (GOOD, {"input": "nothere.mp4"}, 7, "replay param source: no such file or folder nothere.mp4"),
    (GOOD, {"input": "x", "rate": "fast"}, 7, "replay param rate: expected a number >= 0, got 'fast'"),
    (GOOD.replace("out-$(var rate).mcap", "kept.mcap"), {"input": "x"}, 11,
     "recorder param output: kept.mcap already exists"),
    (GOOD + "  replay:\n    node: replay\n", {"input": "x"}, 12, "'replay' is given twice (lines 5 and 12) under nodes"),
    (GOOD.replace("rate: $(var rate)}", "rate: $(var rate), rate: 2}"), {"input": "x"}, 7,
     "'rate' is given twice"),
    ("nodes: []\n", {}, 1, "'nodes:' must map"),
    ("nodez: {}\n", {}, 1, "unknown key 'nodez'"),
])
def test_bad_files_are_rejected_with_file_and_line(tmp_path, text, args, line, words):
    path = write(tmp_path, text)
    with pytest.raises(LaunchError) as e:
        load_launch_file(path, args)
    assert str(e.value).startswith(f"{path}:{line}:"), str(e.value)
    assert words in str(e.value)


def test_missing_file_and_cli_exit_code(tmp_path, run_dir):
    r = subprocess.run([sys.executable, "-m", "handmocap.runtime.launch", str(tmp_path / "nope.yaml")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip() == f"handlaunch: error: {tmp_path / 'nope.yaml'}: no such launch file"
    assert not list(run_dir.iterdir())   # nothing was started


def test_bad_file_starts_no_process(tmp_path, run_dir):
    path = write(tmp_path, GOOD.replace("node: recorder", "node: nope"))
    r = subprocess.run([sys.executable, "-m", "handmocap.runtime.launch", str(path), "input:=x"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "unknown node type 'nope'" in r.stderr
    assert "Traceback" not in r.stderr and not list(run_dir.iterdir())


OPTIONAL = """\
args:
  bag: {default: ""}
nodes:
  replay:
    node: replay
    params: {source: clip.mp4}
  recorder:
    node: recorder
    params: {output: $(var bag)}
    if: $(var bag)
"""


@pytest.mark.parametrize("args, names", [
    ({}, ["replay"]),                                   # empty default: switched off
    ({"bag": "out.mcap"}, ["replay", "recorder"]),
    ({"bag": False}, ["replay"]), ({"bag": "off"}, ["replay"]), ({"bag": None}, ["replay"]),
])
def test_if_switches_a_node_on_and_off(tmp_path, args, names):
    lf = load_launch_file(write(tmp_path, OPTIONAL), args)
    assert [n.name for n in lf.nodes] == names


def test_a_model_file_is_checked_only_for_a_node_that_runs(tmp_path):
    text = GOOD + "  detector:\n    node: detector\n    if: $(var rate)\n    params: {detnet: nothere.onnx}\n"
    assert [n.name for n in load_launch_file(write(tmp_path, text), {"input": "x", "rate": 0}).nodes] == \
        ["replay", "recorder"]
    with pytest.raises(LaunchError, match="detector param detnet: no such file nothere.onnx"):
        load_launch_file(write(tmp_path, text), {"input": "x", "rate": 1})


def test_documented_off_values_pass_the_checks(tmp_path):
    """A rate cap of 0 is the bridge's documented "off"; the checks must not refuse it."""
    text = GOOD + "  bridge:\n    node: bridge\n    params: {image_hz: 0, mesh_hz: 0}\n"
    assert [n.name for n in load_launch_file(write(tmp_path, text), {"input": "x"}).nodes] == \
        ["replay", "recorder", "bridge"]


def test_a_switched_off_node_is_still_checked(tmp_path):
    path = write(tmp_path, OPTIONAL.replace("params: {output: $(var bag)}", "params: {outptu: x}"))
    with pytest.raises(LaunchError) as e:
        load_launch_file(path, {})
    assert str(e.value).startswith(f"{path}:9:") and "has no parameter 'outptu'" in str(e.value)
    path = write(tmp_path, OPTIONAL.replace("if: $(var bag)", "if: [a]"))
    with pytest.raises(LaunchError, match="'if' must be a value"):
        load_launch_file(path, {})


@pytest.mark.parametrize("name", ["demo", "replay", "webcam", "depthai"])
def test_product_launch_files_are_valid(name, monkeypatch):
    """Every shipped graph passes the launcher's checks with its defaults (input for replay),
    run from the repository's root as the README runs them."""
    monkeypatch.chdir(ROOT)
    args = {"input": "data/demo/hand_clip.mp4", "bag": str(ROOT / "no-such-dir" / "r.mcap")} if name == "replay" else {}
    lf = load_launch_file(ROOT / "launch" / f"{name}.yaml", args)
    names = [n.name for n in lf.nodes]
    assert "visualizer" in names or name == "replay"
    assert ("recorder" in names) == (name in ("demo", "replay"))   # live graphs record only with bag:=


def test_an_argument_given_twice_is_an_error_naming_both(tmp_path, run_dir):
    path = write(tmp_path, GOOD)
    r = subprocess.run([sys.executable, "-m", "handmocap.runtime.launch", str(path), "input:=a.mp4", "rate:=1", "rate:=2"],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip() == "handlaunch: error: rate is given twice: rate:=1 and 'rate:=2'"
    assert not list(run_dir.iterdir())


def test_a_topic_cycle_is_refused_before_any_message(tmp_path, run_dir):
    """ticker -> /b -> r1 -> /c -> r2 -> /b: r1 and r2 would each wait for the other's end of
    stream for ever; the launcher names the cycle once every node is up, before the first
    message, and stops the graph."""
    from conftest import handlaunch
    path = write(tmp_path, """
nodes:
  ticker: {node: graphnodes.ticker, params: {topic: /b, count: 5}}
  r1: {node: graphnodes.relay, params: {input: /b, output: /c}}
  r2: {node: graphnodes.relay, params: {input: /c, output: /b}}
""")
    r = handlaunch([path], run_dir, timeout=60)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "error: topic cycle r1 -[/c]-> r2 -[/b]-> r1" in r.stdout, r.stdout


def test_topic_cycle_finds_cycles_and_only_cycles():
    from handmocap.runtime.bus import NodeInfo
    from handmocap.runtime.launch import topic_cycle
    node = lambda name, pub=(), sub=(), **kw: NodeInfo(name, 1, "", {t: "Blob" for t in pub}, {t: "all" for t in sub}, **kw)
    chain = {"s": node("s", ["/a"]), "m": node("m", ["/b"], ["/a"]), "rec": node("rec", [], ["*"]),
             "echo": node("echo", [], ["*"], observer=True)}
    assert topic_cycle(chain) is None
    assert topic_cycle({**chain, "back": node("back", ["/a"], ["/b"])}) == "back -[/a]-> m -[/b]-> back"
    assert topic_cycle({"self": node("self", ["/x"], ["*"])}) == "self -[/x]-> self"


def test_product_launch_files_work_from_any_folder(tmp_path, monkeypatch):
    """$(dirname) makes the files a launch file names beside it (the demo clip, the toy robot)
    resolve from wherever handlaunch is started, not only from the repository's root."""
    monkeypatch.chdir(tmp_path)
    demo = load_launch_file(ROOT / "launch" / "demo.yaml", {})
    source = next(n for n in demo.nodes if n.name == "replay").params["source"]
    assert Path(source).is_file() and Path(source).resolve() == (ROOT / "data/demo/hand_clip.mp4").resolve()


def test_the_readme_arguments_exist_in_the_product_launch_files():
    """`mesh:=false` (a bare install, no OpenGL) and the demo's `loop:=true` (time for a second
    terminal) are arguments of the launch files the README names, and reach their nodes."""
    root = Path(__file__).resolve().parent.parent
    demo = {n.name: n for n in load_launch_file(root / "launch" / "demo.yaml", {"mesh": False, "loop": True}).nodes}
    assert demo["visualizer"].params["mesh"] is False and demo["replay"].params["loop"] is True
    webcam = {n.name: n for n in load_launch_file(root / "launch" / "webcam.yaml", {"mesh": False}).nodes}
    assert webcam["visualizer"].params["mesh"] is False


@pytest.mark.parametrize("name", ["webcam", "replay", "ros2"])
def test_the_finder_argument_reaches_the_detector(name, monkeypatch):
    """`finder:=models/finder_lite0_int8.onnx` (the README's advice for a camera above a desk)
    is an argument of the graphs a user runs and reaches the detector; a missing file is the
    launcher's one error naming the param and the file."""
    monkeypatch.chdir(ROOT)
    base = {"input": "data/demo/hand_clip.mp4"} if name == "replay" else {}
    nodes = {n.name: n for n in load_launch_file(ROOT / "launch" / f"{name}.yaml",
                                                 {**base, "finder": "models/finder_lite0_int8.onnx"}).nodes}
    assert nodes["detector"].params["finder"] == "models/finder_lite0_int8.onnx"
    default = {n.name: n for n in load_launch_file(ROOT / "launch" / f"{name}.yaml", base).nodes}
    assert default["detector"].params["finder"] is None                 # null: models/finder.onnx
    with pytest.raises(LaunchError, match="detector param finder: no such file models/nothere.onnx"):
        load_launch_file(ROOT / "launch" / f"{name}.yaml", {**base, "finder": "models/nothere.onnx"})


@pytest.mark.parametrize("name", ["webcam", "teleop", "ros2", "depthai"])
def test_live_graphs_respawn_their_perception_container_at_once(name):
    """A live graph's perception container (source, detector, shape, ik) respawns after a
    crash within 0.2 s (benchmarks/drill_respawn.py: poses back in under a second); the
    offline ones (replay, demo) do not, a failed replay is a result."""
    from handmocap.runtime.launch import processes
    live = {p.name: p for p in processes(load_launch_file(ROOT / "launch" / f"{name}.yaml", {}).nodes)}
    assert live["perception"].respawn and live["perception"].respawn_delay <= 0.2 and live["perception"].required
    clip = str(ROOT / "data" / "demo" / "hand_clip.mp4")
    offline = {p.name: p for p in processes(load_launch_file(ROOT / "launch" / "replay.yaml", {"input": clip}).nodes)}
    assert not offline["perception"].respawn


def test_the_launcher_runs_without_numpy_or_the_codec():
    """handlaunch only starts and watches processes: it imports no numpy, OpenCV, onnxruntime
    or msgpack, so the supervisor of every graph stays small (benchmarks/bench_memory.py)."""
    heavy = ("numpy", "cv2", "onnxruntime", "msgpack", "handmocap.runtime.codec")
    r = subprocess.run([sys.executable, "-c", "import sys, handmocap.runtime.launch; "
                        f"print([m for m in {heavy!r} if m in sys.modules])"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


def test_nodes_keep_compiled_modules_in_a_cache_where_bytecode_writes_are_off(tmp_path, run_dir):
    """Where PYTHONDONTWRITEBYTECODE is set, a node process (and a respawned one) would compile
    the package's modules again at each start: handlaunch gives its nodes a bytecode cache in
    the user's cache folder instead (bytecode_env), nothing beside the sources; a prefix of the
    user's own, or no such setting, is left alone."""
    from conftest import graph_env
    from handmocap.runtime.launch import bytecode_env
    env = {"HOME": "/h", "PYTHONDONTWRITEBYTECODE": "1"}
    assert bytecode_env(env) == {"HOME": "/h", "PYTHONPYCACHEPREFIX": "/h/.cache/handmocap/pycache"}
    assert bytecode_env({**env, "XDG_CACHE_HOME": "/c"})["PYTHONPYCACHEPREFIX"] == "/c/handmocap/pycache"
    for kept in ({**env, "PYTHONPYCACHEPREFIX": "/mine"}, {"HOME": "/h"}, {"PYTHONDONTWRITEBYTECODE": "1"}):
        assert bytecode_env(kept) == kept
    g = write(tmp_path, "nodes:\n  ticker: {node: graphnodes.ticker, params: {count: 3}, required: true}\n")
    cache = tmp_path / "cache"
    launch_env = {**graph_env(run_dir), "PYTHONDONTWRITEBYTECODE": "1", "XDG_CACHE_HOME": str(cache)}
    launch_env.pop("PYTHONPYCACHEPREFIX", None)
    r = subprocess.run([sys.executable, "-m", "handmocap.runtime.launch", str(g)], capture_output=True, text=True,
                       timeout=60, env=launch_env)
    assert r.returncode == 0, r.stdout + r.stderr
    compiled = {p.name for p in (cache / "handmocap" / "pycache").rglob("*.pyc")}
    assert {f"node.{sys.implementation.cache_tag}.pyc", f"ticker.{sys.implementation.cache_tag}.pyc"} <= compiled
