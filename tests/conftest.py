import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = ROOT.parent / "shared" / "data"

# the suite starts several hundred Python processes (nodes, graphs, CLIs): where
# PYTHONDONTWRITEBYTECODE is set (CI runners, container images) each would compile the package's
# modules again, so they share the bytecode cache handlaunch gives its nodes
from handmocap.runtime.launch import bytecode_env  # noqa: E402
_env = bytecode_env(os.environ)
if _env != dict(os.environ):
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    os.environ.update(_env)


@pytest.fixture
def run_dir(monkeypatch):
    """A private graph: its own run dir (short, for unix socket paths), in this process and children."""
    d = tempfile.mkdtemp(prefix="hm")
    monkeypatch.setenv("HANDMOCAP_RUN_DIR", d)
    yield Path(d)
    shutil.rmtree(d, ignore_errors=True)


def paths_in(obj, prefix=()):
    """Every place in a message's nested dicts and lists, as key/index tuples (the message itself
    first, as ())."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from paths_in(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from paths_in(v, prefix + (i,))


def graph_env(run_dir: Path, **extra) -> dict:
    """Environment for a handlaunch subprocess: private run dir, test nodes importable."""
    env = {**os.environ, "HANDMOCAP_RUN_DIR": str(run_dir), "HANDMOCAP_VALIDATE_SEND": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    env.update(extra)
    return env


def draw_bar_and_number(i, img):
    """Test frame i: a red bar 20 + 20 i px wide from the left edge and the number i, so every
    frame differs (drawn into img, a (H,W,3) uint8 BGR canvas)."""
    import cv2
    img[:, : 20 + 20 * i] = (0, 0, 255)
    cv2.putText(img, str(i), (150, 140), cv2.FONT_HERSHEY_SIMPLEX, 2, (255, 255, 255), 3)


def write_test_video(path, n, size=(320, 240), fourcc="MJPG", draw=draw_bar_and_number, background=0,
                     folder=None):
    """Write an n-frame 30 fps test video to `path` (size = (width, height) px; fourcc e.g.
    MJPG in .avi, mp4v in .mp4): frame i is `draw(i, img)` on a (H,W,3) uint8 canvas filled
    with `background`; with `folder`, each frame is also saved there as NNNN.png. Returns the
    frames as OpenCV decodes the written file: a list of n (H,W,3) uint8 BGR images."""
    import cv2
    import numpy as np

    from handmocap.runtime.frames import read_video
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30, (w, h))
    if folder is not None:
        Path(folder).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        img = np.full((h, w, 3), background, np.uint8)
        draw(i, img)
        writer.write(img)
        if folder is not None:
            cv2.imwrite(str(Path(folder) / f"{i:04d}.png"), img)
    writer.release()
    frames = read_video(path)
    assert len(frames) == n, f"{path}: wrote {n} frames, read back {len(frames)}"
    return frames


def handlaunch(args, run_dir, timeout=60, during=None, **kw):
    """Run handlaunch to its end (CompletedProcess); `during()`, if given, runs while the graph
    does (a drill: kill a node, ...), its stdout and stderr then come as one in stdout."""
    cmd = [sys.executable, "-m", "handmocap.runtime.launch", *map(str, args)]
    if during is None:
        return subprocess.run(cmd, env=graph_env(run_dir), capture_output=True, text=True, timeout=timeout, **kw)
    proc = subprocess.Popen(cmd, env=graph_env(run_dir), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, **kw)
    try:
        during()
        out, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=30)
    return subprocess.CompletedProcess(cmd, proc.returncode, out, "")


# -- the demo chain as a launched graph (test_e2e, test_drills) ---------------------------
DEMO_CLIP = ROOT / "data" / "demo" / "hand_clip.mp4"   # 640x480, 30 fps, 90 frames
DEMO_TRUTH = ROOT / "data" / "demo" / "hand_clip.npz"  # its ground truth (scripts/render_demo_clip.py)


def chain_yaml(source, bag, rate=1.0, loop=False, detector="", extra_nodes="", replay_params="", source_entry=None,
               detector_params="", recorder_params=""):
    """Launch-file text of launch/demo.yaml's chain, replay -> detector -> shape -> ik ->
    recorder, written by the tests themselves (demo.yaml is the product's and changes; its
    visualizer is not under test here). `detector`: extra keys of the detector entry (e.g.
    "respawn: true"); `extra_nodes`: more node entries, one per line, two-space indented;
    `replay_params`: more replay params (", calibration: FILE"); `source_entry`: another source
    node's entry instead of replay's ("camera: {node: camera, ...}"); `detector_params`: more
    detector params (", detnet: FILE"); `recorder_params`: more recorder params (", split_s: 1")."""
    source_entry = source_entry or (f'replay: {{node: replay, params: {{source: "{source}", rate: {rate}, '
                                    f'loop: {str(loop).lower()}{replay_params}}}, required: true}}')
    return f"""
nodes:
  {source_entry}
  detector: {{node: detector, params: {{every_frame: true{detector_params}}}, required: true{', ' + detector if detector else ''}}}
  shape: {{node: shape}}
  ik: {{node: ik, required: true}}
  recorder: {{node: recorder, params: {{output: "{bag}", overwrite: true, raw: true{recorder_params}}}, required: true}}
{extra_nodes}"""


class LiveGraph:
    """handlaunch on a launch file, a process of its own with its output collected (live_graph)."""

    def __init__(self, lf, run_dir):
        self.proc = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)],
                                     env=graph_env(run_dir), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.out, self.returncode = "", None

    def finish(self, timeout=60):
        """Wait for the graph to end by itself; its output and exit code are then .out, .returncode."""
        self.out, _ = self.proc.communicate(timeout=timeout)
        self.returncode = self.proc.returncode
        return self

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.finish(timeout=30)


@contextlib.contextmanager
def live_graph(lf, run_dir):
    """`with live_graph(lf, run_dir) as g:` a graph to drive (kill its nodes, wait for poses)
    and then g.finish(); one still running when the block ends (a failed wait) is stopped."""
    g = LiveGraph(lf, run_dir)
    try:
        yield g
    finally:
        g.stop()


def read_bag(path):
    """{topic: [(decoded message, log time ns = the recorder's receive time)]} of a bag, in order."""
    from handmocap.runtime import codec
    from handmocap.runtime.bag import iter_messages
    out = {}
    for topic, type_name, payload, log_ns in iter_messages(path):
        out.setdefault(topic, []).append((codec.decode(payload, type_name), log_ns))
    return out


def pose_latencies_ms(bag_msgs):
    """(N,) ms from each /hand/pose's capture stamp to its receipt by the recorder, in order."""
    import numpy as np
    return np.array([(log_ns - m["header"]["stamp_ns"]) / 1e6 for m, log_ns in bag_msgs.get("/hand/pose", [])])


# -- a running graph's node files (heartbeats) ---------------------------------------------
def node_file(run_dir, name):
    try:
        return json.loads((run_dir / f"{name}.json").read_text())
    except (OSError, ValueError):
        return None


def wait_until(what, predicate, timeout_s=60):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def published(run_dir, name, topic):
    """How many messages node `name` says (in its heartbeat file, every 0.5 s) it published on topic."""
    info = node_file(run_dir, name)
    return info["stats"]["published"].get(topic, 0) if info and info.get("stats") else 0
