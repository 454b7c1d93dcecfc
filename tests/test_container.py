"""Containers (launch key `container:`): several nodes as threads of one process, talking over
inproc://, still visible to every other process of the graph (recorder, handtopic)."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import DEMO_CLIP, graph_env, handlaunch, node_file, published, read_bag, wait_until
from handmocap.runtime.launch import ContainerSpec, LaunchError, load_launch_file, processes


def chain(bag, rate=0, loop=False, container="perception", detector="", shape="", ik="", source_inside=False,
          source=None, source_entry=None):
    """The demo chain; `source_inside`: the source in the container too (as the product's launch
    files have it); `source`: another video; `source_entry`: another source node's entry."""
    c = f", container: {container}" if container else ""
    cs = c if source_inside else ""
    source_entry = source_entry or (f'replay: {{node: replay, params: {{source: "{source or DEMO_CLIP}", rate: {rate}, '
                                    f'loop: {str(loop).lower()}}}, required: true{cs}}}')
    return f"""
nodes:
  {source_entry}
  detector: {{node: detector, params: {{every_frame: true{detector}}}, required: true{c}}}
  shape: {{node: shape{shape}{c}}}
  ik: {{node: ik, required: true{c}{ik}}}
  recorder: {{node: recorder, params: {{output: "{bag}", overwrite: true, raw: true}}, required: true}}
"""


def write(tmp_path, text):
    p = tmp_path / "g.yaml"
    p.write_text(text)
    return p


def test_container_groups_nodes_into_one_process(tmp_path):
    lf = load_launch_file(write(tmp_path, chain(tmp_path / "o.mcap", detector="", ik=", respawn: true, "
                                                "respawn_delay: 0.3")), {})
    procs = processes(lf.nodes)
    assert [p.name for p in procs] == ["replay", "perception", "recorder"]
    c = procs[1]
    assert isinstance(c, ContainerSpec) and [m.name for m in c.members] == ["detector", "shape", "ik"]
    assert c.required and c.respawn and c.respawn_delay == 0.3


@pytest.mark.parametrize("replace, words", [
    ("container: perception}\n  shape", "bad container name"),
    ("container: perception}\n  shape", "has the name of a node"),
    ("shape: {node: shape, container: perception}", "its environment differs"),
])
def test_bad_containers_are_rejected_with_file_and_line(tmp_path, replace, words):
    text = chain(tmp_path / "o.mcap")
    if words == "bad container name":
        text = text.replace(replace, "container: 9lives}\n  shape", 1)
    elif words == "has the name of a node":
        text = text.replace(replace, "container: recorder}\n  shape", 1)
    else:
        text = text.replace(replace, "shape: {node: shape, container: perception, env: {A: b}}")
    path = write(tmp_path, text)
    with pytest.raises(LaunchError) as e:
        load_launch_file(path, {})
    assert str(e.value).startswith(f"{path}:") and words in str(e.value), str(e.value)


def start_graph(lf, run_dir):
    return subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=graph_env(run_dir),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def node_files_while_running(proc, run_dir, names, timeout_s=60):
    """{name: node file} of every node in `names` as soon as each has written one (a short
    graph's files go when it ends, so they are read while it runs)."""
    files = {}
    deadline = time.monotonic() + timeout_s
    while proc.poll() is None and len(files) < len(names) and time.monotonic() < deadline:
        for name in names:
            info = node_file(run_dir, name)
            if info and "pid" in info:
                files[name] = info
        time.sleep(0.02)
    return files


def kill_the_container_midway(lf, run_dir, member):
    """Run the looping graph `lf`; after 30 poses SIGKILL the container that holds ik and
    `member`, wait until it is back (one new pid for both) with 30 more poses, then end the
    source with SIGTERM. Returns (handlaunch's exit code, its output, the kill's time ns)."""
    proc = start_graph(lf, run_dir)

    def pid(name):
        return (node_file(run_dir, name) or {}).get("pid")

    def poses():
        return published(run_dir, "ik", "/hand/pose")

    try:
        wait_until("30 poses", lambda: poses() >= 30)
        victim = pid("ik")
        assert pid(member) == victim
        kill_ns = time.time_ns()
        os.kill(victim, signal.SIGKILL)
        wait_until("a new container", lambda: pid("ik") not in (None, victim) and pid(member) == pid("ik"))
        wait_until("30 poses after the respawn", lambda: poses() >= 30)
        os.kill(pid("replay"), signal.SIGTERM)   # ends the source; its end-of-stream ends the graph
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=30)
    return proc.returncode, out, kill_ns


def test_container_delivers_every_pose_to_a_recorder_outside_it(tmp_path, run_dir):
    """detector + shape + ik in one process; replay and the recorder are processes of their
    own: the recorder gets every frame's keypoints, shape and pose (published inside the
    container, received outside), and the container's nodes run in one pid."""
    bag = tmp_path / "o.mcap"
    proc = start_graph(write(tmp_path, chain(bag)), run_dir)
    pids = {name: (info["pid"], info.get("inproc")) for name, info in
            node_files_while_running(proc, run_dir, ("replay", "detector", "shape", "ik", "recorder")).items()}
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0 and "all nodes finished" in out, out
    assert "started 5 node(s)" in out and "in 3 processes" in out, out
    assert "[detector] INFO" in out and "Traceback" not in out, out   # the node's own name on its lines
    assert pids["detector"][0] == pids["shape"][0] == pids["ik"][0] != pids["replay"][0] != pids["recorder"][0]
    assert pids["ik"][1]["endpoint"] == "inproc://ik" and pids["replay"][1] is None
    msgs = read_bag(bag)
    images = [m["header"]["stamp_ns"] for m, _ in msgs["/camera/image"]]
    assert len(images) == 90
    for topic in ("/hand/keypoints", "/hand/shape", "/hand/pose"):
        assert [m["header"]["stamp_ns"] for m, _ in msgs[topic]] == images, topic
    assert np.mean([len(m["hands"]) == 1 for m, _ in msgs["/hand/pose"]]) >= 0.9


def test_killed_container_respawns_and_poses_resume(tmp_path, run_dir):
    """As the killed-detector drill (test_drills), with the detector in a container: SIGKILL
    takes the whole container (detector, shape, ik) down; it respawns as one and poses resume."""
    bag = tmp_path / "o.mcap"
    lf = write(tmp_path, chain(bag, rate=1.0, loop=True, ik=", respawn: true, respawn_delay: 0.2"))
    returncode, out, _ = kill_the_container_midway(lf, run_dir, "detector")
    assert returncode == 0 and "all nodes finished" in out, out
    assert "container perception (detector, shape, ik) died (killed by signal 9); respawn in 0.2 s" in out, out
    assert "respawning perception" in out and "Traceback" not in out, out
    kill_poses = [m for m, _ in read_bag(bag)["/hand/pose"]]
    assert len(kill_poses) >= 60


def corrupt_model(tmp_path):
    """A DetNet file that exists (the launcher's check passes) but cannot be loaded: the
    detector node fails as it starts, inside its container."""
    path = tmp_path / "bad.onnx"
    path.write_bytes(b"xx" * 99)
    return path


def test_failed_required_node_in_a_container_is_one_clear_error(tmp_path, run_dir):
    lf = write(tmp_path, chain(tmp_path / "o.mcap", detector=f", detnet: {corrupt_model(tmp_path)}"))
    r = handlaunch([lf], run_dir, timeout=120)
    seen = r.stdout + r.stderr
    assert r.returncode == 1, seen
    assert "Traceback" not in seen, seen
    errors = [line for line in seen.splitlines() if "ERROR" in line or "error" in line.lower()]
    assert len(errors) == 2, seen
    assert errors[0].startswith("[detector] ERROR ") and "bad.onnx" in errors[0], seen
    assert errors[1] == ("[handlaunch] error: required container perception (detector, shape, ik) failed "
                         "(exit code 2); stopping the graph"), seen


def test_failed_optional_node_in_a_container_leaves_the_others_running(tmp_path, run_dir):
    bag = tmp_path / "o.mcap"
    bad = tmp_path / "bad.npz"        # loads only inside the node (a missing file: the launcher's error)
    bad.write_bytes(b"not a hand model")
    lf = write(tmp_path, chain(bag, shape=f", params: {{model: {bad}}}"))
    r = handlaunch([lf], run_dir, timeout=120)
    seen = r.stdout + r.stderr
    assert r.returncode == 0 and "all nodes finished" in seen, seen
    assert "[shape] ERROR" in seen and "node shape failed (exit code 2); the container goes on without it" in seen
    assert len(read_bag(bag)["/hand/pose"]) == 90


# -- the source inside the container (the product's launch files) -----------------------------
@pytest.mark.parametrize("name, source", [("demo", "replay"), ("replay", "replay"), ("webcam", "camera"),
                                          ("depthai", "depthai")])
def test_product_launch_files_compose_the_source_with_perception(name, source):
    """The frames reach the detector in-process; the recorder, visualizer and bridge are
    processes of their own and get /camera/image over ipc."""
    from conftest import ROOT
    args = {"input": str(ROOT / "data" / "demo" / "hand_clip.mp4")} if name == "replay" else {}
    procs = processes(load_launch_file(ROOT / "launch" / f"{name}.yaml", args).nodes)
    containers = [p for p in procs if isinstance(p, ContainerSpec)]
    assert len(containers) == 1 and containers[0].name == "perception"
    assert [m.name for m in containers[0].members] == [source, "detector", "shape", "ik"]
    assert containers[0].required
    assert all(not isinstance(p, ContainerSpec) for p in procs if p is not containers[0])


def test_source_in_the_container_sends_every_frame_to_a_recorder_outside_it(tmp_path, run_dir):
    """replay, detector, shape, ik in one process: the recorder (another process) still gets
    every frame over ipc, byte for byte decodable, and every frame's pose."""
    bag = tmp_path / "o.mcap"
    proc = start_graph(write(tmp_path, chain(bag, source_inside=True)), run_dir)
    pids = {name: info["pid"] for name, info in
            node_files_while_running(proc, run_dir, ("replay", "detector", "shape", "ik", "recorder")).items()}
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0 and "all nodes finished" in out, out
    assert "started 5 node(s)" in out and "in 2 processes" in out and "Traceback" not in out, out
    assert pids["replay"] == pids["detector"] == pids["ik"] != pids["recorder"]
    msgs = read_bag(bag)
    from handmocap.runtime.frames import read_video
    frames = read_video(DEMO_CLIP)
    assert len(msgs["/camera/image"]) == len(frames) == 90
    for (m, _), f in zip(msgs["/camera/image"][::15], frames[::15]):
        np.testing.assert_array_equal(m["data"], f)
    images = [m["header"]["stamp_ns"] for m, _ in msgs["/camera/image"]]
    for topic in ("/camera/info", "/hand/keypoints", "/hand/shape", "/hand/pose"):
        assert [m["header"]["stamp_ns"] for m, _ in msgs[topic]] == images, topic
    assert np.mean([len(m["hands"]) == 1 for m, _ in msgs["/hand/pose"]]) >= 0.9


def one_error(r, node, words):
    """handlaunch's output holds one line naming the cause (from `node`) and the launcher's
    verdict on the container; exit code 1; no traceback."""
    seen = r.stdout + r.stderr
    assert r.returncode == 1, seen
    assert "Traceback" not in seen and "File \"" not in seen, seen
    errors = [line for line in seen.splitlines() if "ERROR" in line or "error" in line.lower()]
    assert len(errors) == 2, seen
    assert errors[0].startswith(f"[{node}] ERROR ") and all(w in errors[0] for w in words), seen
    assert errors[1].startswith("[handlaunch] error: required container perception (") \
        and errors[1].endswith("failed (exit code 2); stopping the graph"), seen
    return seen


def test_corrupt_video_with_the_source_in_the_container(tmp_path, run_dir):
    """The drill's corrupt-in-the-middle video, replay inside the container: one line names the
    cause, the graph fails, and what the recorder got before is in its bag."""
    from test_drills import corrupt_middle
    bag = tmp_path / "o.mcap"
    lf = write(tmp_path, chain(bag, source_inside=True, source=corrupt_middle(tmp_path / "cut.mp4")))
    r = handlaunch([lf], run_dir, timeout=120)
    one_error(r, "replay", ["cut.mp4", "decoding stopped at frame", "of 90", "corrupt"])
    msgs = read_bag(bag)
    assert len(msgs.get("/camera/image", [])) >= 1, "frames sent before the failure are in the bag"


def test_camera_that_cannot_open_in_the_container(tmp_path, run_dir):
    lf = write(tmp_path, chain(tmp_path / "o.mcap", source_entry="camera: {node: camera, params: {device: /dev/video99}, "
                                                                  "required: true, container: perception}"))
    r = handlaunch([lf], run_dir, timeout=120)
    one_error(r, "camera", ["/dev/video99", "no such device"])


def test_unloadable_model_with_the_source_in_the_container(tmp_path, run_dir):
    lf = write(tmp_path, chain(tmp_path / "o.mcap", source_inside=True, detector=f", detnet: {corrupt_model(tmp_path)}"))
    r = handlaunch([lf], run_dir, timeout=120)
    seen = one_error(r, "detector", ["bad.onnx", "cannot be loaded"])
    assert "perception (replay, detector, shape, ik)" in seen


def test_killed_container_with_the_source_respawns_and_poses_resume(tmp_path, run_dir):
    """SIGKILL takes source and perception down together; the container respawns as one (the
    source starts its video again) and every frame after it has its pose."""
    bag = tmp_path / "o.mcap"
    lf = write(tmp_path, chain(bag, rate=1.0, loop=True, source_inside=True, ik=", respawn: true, respawn_delay: 0.2"))
    returncode, out, kill_ns = kill_the_container_midway(lf, run_dir, "replay")
    assert returncode == 0 and "all nodes finished" in out, out
    assert "container perception (replay, detector, shape, ik) died (killed by signal 9); respawn in 0.2 s" in out, out
    assert "Traceback" not in out, out
    msgs = read_bag(bag)
    images = np.array([m["header"]["stamp_ns"] for m, _ in msgs["/camera/image"]])
    poses_ = np.array([m["header"]["stamp_ns"] for m, _ in msgs["/hand/pose"]])
    assert (poses_ < kill_ns).sum() >= 30 and (poses_ > kill_ns).sum() >= 30
    # every frame after the respawn has its pose, but for the last few: SIGTERM stops the
    # container's nodes together (as Ctrl-C stops a graph), the one in flight may go unposed
    after = images[images > kill_ns]
    assert np.isin(after[:-3], poses_).all()


def test_a_slow_keep_all_image_subscriber_outside_does_not_hold_the_source(tmp_path, run_dir):
    """The source in the container, a keep-all consumer of /camera/image in another process
    that takes 200 ms a frame (6x slower than the camera): zmq queues the frames for it up to
    its bounded queue (bus: Queues, 32 + 32 frames); the source keeps the 30 fps clock and the poses'
    latency stays that of a frame's processing, not of the slow consumer's backlog; the
    consumer gets the frames in order, and those its queue could not hold are counted lost."""
    bag = tmp_path / "o.mcap"
    sink = (f"  slow: {{node: graphnodes.sink, params: {{topic: /camera/image, mode: all, work_s: 0.2, "
            f"out: {tmp_path}/slow.json}}}}\n")
    lf = write(tmp_path, chain(bag, rate=1.0, source_inside=True) + sink)
    r = handlaunch([lf], run_dir, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    msgs = read_bag(bag)
    images = np.array([m["header"]["stamp_ns"] for m, _ in msgs["/camera/image"]]) / 1e9
    assert len(images) == 90
    late = (images - images[0]) - np.arange(90) / 30.0
    assert np.median(late) < 0.01 and late.max() < 0.5, late   # the source was not held up
    lat = np.array([(log_ns - m["header"]["stamp_ns"]) / 1e6 for m, log_ns in msgs["/hand/pose"]])
    assert len(lat) == 90 and np.median(lat[30:]) < 100, lat   # not the consumer's seconds of backlog
    seen = json.loads((tmp_path / "slow.json").read_text())
    seqs = np.array(seen["seqs"])
    assert seqs[0] == 0 and (np.diff(seqs) > 0).all() and max(seen["ages_ms"]) > 3000, seen["ages_ms"][-3:]
    assert seen["lost"] > 0 and len(seqs) + seen["lost"] == 90, (len(seqs), seen["lost"])
