"""The examples: examples/subscribe_pose.py against a real running graph, the dex-retargeting
input conversion (handmocap.perception.retarget) on known poses, and examples/in_process.py (HandTracker on a video and a
photo); the README shows the first and the last as they are."""
import importlib.util
import json
import re
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import ROOT, graph_env
from graphnodes.pose_source import synthetic_pose_hands
from handmocap.perception import camera_info
from handmocap.perception.hand_model import HandModel
from handmocap.perception import retarget as dex
from handmocap.perception.rotations import mirror_points

EXAMPLES = ROOT / "examples"
SOURCE_ROOT = [0.02, -0.01, 0.5]   # where the graph's pose source puts the hand's root, metres


def load_example(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module




def lines_of(path, n, proc, deadline):
    """The first n whole lines a subprocess wrote to `path`, waiting for them until `deadline`.
    A line still being written (no newline yet) is not counted: print() may reach the file in
    more than one write, and the test reads between them."""
    while True:
        lines = path.read_text().split("\n")[:-1] if path.exists() else []
        if len(lines) >= n:
            return lines
        assert proc.poll() is None, path.read_text()
        assert time.monotonic() < deadline, lines
        time.sleep(0.1)


def test_subscribe_pose_prints_the_hands_of_a_running_graph(tmp_path, run_dir):
    """A graph whose `ik` node (a stand-in publishing known HandPose messages) runs; the example
    finds it through the run dir's node file, or is given the endpoint, and prints each hand."""
    lf = tmp_path / "g.yaml"
    lf.write_text(f"""
nodes:
  ik: {{node: graphnodes.pose_source, params: {{hz: 20, handedness: left, root: {SOURCE_ROOT}}}}}
""")
    graph = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=graph_env(run_dir),
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    outputs = []
    try:
        deadline = time.monotonic() + 60
        while not (run_dir / "ik.json").exists():
            assert time.monotonic() < deadline and graph.poll() is None
            time.sleep(0.1)
        endpoint = json.loads((run_dir / "ik.json").read_text())["endpoint"]
        for args in ([], [endpoint]):
            out = tmp_path / f"out{len(args)}.txt"
            with open(out, "w") as f:
                proc = subprocess.Popen([sys.executable, str(EXAMPLES / "subscribe_pose.py"), *args],
                                        env=graph_env(run_dir), stdout=f, stderr=subprocess.STDOUT, text=True)
            try:
                outputs.append(lines_of(out, 3, proc, time.monotonic() + 60))
            finally:
                proc.terminate()
                proc.wait(timeout=10)
    finally:
        graph.terminate()
        graph.communicate(timeout=30)
    # copyable: pyzmq, msgpack, numpy only
    assert not re.search(r"^\s*(import|from) handmocap", (EXAMPLES / "subscribe_pose.py").read_text(), re.M)
    number = r"-?\d+\.\d*"
    vec = lambda n: r"\[\s*" + r"\s+".join([number] * n) + r"\s*\]"
    line = re.compile(rf"^(\d+) left wrist_m ({vec(3)}) q_wrist ({vec(4)}) q_index_proximal ({vec(4)})$")
    for lines in outputs:
        for text in lines[:3]:
            m = line.match(text)
            assert m, text
            assert int(m[1]) > 1_600_000_000 * 10**9                   # a capture stamp, ns
            wrist = np.array(m[2].strip("[] ").split(), float)
            assert np.linalg.norm(wrist - SOURCE_ROOT) < 0.2            # a hand's length from its root
            for q in (m[3], m[4]):
                assert np.linalg.norm(np.array(q.strip("[] ").split(), float)) == pytest.approx(1, abs=0.01)


def test_subscribe_pose_refuses_a_run_dir_others_could_have_made(tmp_path):
    """As handlaunch and handtopic do: a run dir others may write (or not ours) is not read, so
    another user's forged node file can't point the example at forged poses."""
    shared = tmp_path / "run"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)
    (shared / "ik.json").write_text(json.dumps({"endpoint": "ipc:///tmp/forged"}))
    r = subprocess.run([sys.executable, str(EXAMPLES / "subscribe_pose.py")], env={**graph_env(shared)},
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 1 and "is not your private folder" in r.stderr and "mode 777" in r.stderr, r.stderr


def test_readme_shows_the_subscriber_example_as_it_is():
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## Using /hand/pose (teleop)"):]
    block = re.search(r"```python\n(.*?)```", section, re.S)[1]
    assert block == (EXAMPLES / "subscribe_pose.py").read_text()


def test_readme_shows_the_in_process_example_as_it_is_and_it_runs(tmp_path):
    import cv2
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("### In-process, without a graph"):]
    block = re.search(r"```python\n(.*?)```", section, re.S)[1]
    assert block == (EXAMPLES / "in_process.py").read_text()
    clip = ROOT / "data" / "demo" / "hand_clip.mp4"
    cap = cv2.VideoCapture(str(clip))
    cap.set(cv2.CAP_PROP_POS_FRAMES, 45)
    photo = tmp_path / "frame45.jpg"                # one of the clip's frames, as a photo
    cv2.imwrite(str(photo), cap.read()[1])
    out = subprocess.run([sys.executable, str(EXAMPLES / "in_process.py"), str(clip), str(photo)],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert sum(line.startswith("video 0 right") for line in lines) >= 80      # the 90-frame clip's right hand
    assert [line.split()[2] for line in lines if line.startswith(f"photo {photo}")] == ["right"]


@pytest.mark.parametrize("args, word", [(["no_such_clip.mp4"], "no_such_clip.mp4: no frame could be read"),
                                        (["data/demo/hand_clip.mp4", "no_such_photo.jpg"],
                                         "no_such_photo.jpg: not an image OpenCV reads")])
def test_in_process_example_says_what_it_could_not_read(args, word):
    """A missing video or photo is one line and a non-zero exit (it was exit 0, or a traceback)."""
    out = subprocess.run([sys.executable, str(EXAMPLES / "in_process.py"), *args], capture_output=True, text=True,
                         timeout=120, cwd=ROOT)
    assert out.returncode == 1 and word in out.stderr and "Traceback" not in out.stderr, out.stderr


# -- dex-retargeting input ---------------------------------------------------------------------
MODEL = HandModel.load()
K = camera_info.default_K(640, 480)


def known_hands(handedness, n=8):
    return [pose for _, pose in synthetic_pose_hands(n, 3, handedness, 0, SOURCE_ROOT, K, MODEL)]


@pytest.mark.parametrize("handedness", ["right", "left"])
def test_dex_retargeting_input_is_in_the_wrist_frame(handedness):
    for hand in known_hands(handedness):
        xyz = hand["xyz"].astype(np.float64)
        F = dex.wrist_frame(xyz)
        np.testing.assert_allclose(F.T @ F, np.eye(3), atol=1e-9)      # orthonormal
        assert np.linalg.det(F) == pytest.approx(1.0)                   # a rotation
        jp = dex.retargeting_joint_pos(xyz, handedness)
        assert jp.shape == (21, 3)
        np.testing.assert_allclose(jp[0], 0, atol=1e-12)               # wrist at the origin
        # a rigid map: every distance between joints kept, joint by joint (no reordering)
        d = lambda p: np.linalg.norm(p[:, None] - p[None], axis=-1)
        np.testing.assert_allclose(d(jp), d(xyz), atol=1e-9)
        # MANO convention of dex-retargeting: middle MCP on +z; index MCP towards +y (right), -y (left)
        middle = jp[dex.MIDDLE_MCP]
        np.testing.assert_allclose(middle[:2], 0, atol=1e-9)
        assert middle[2] == pytest.approx(np.linalg.norm(xyz[9] - xyz[0]))
        assert abs(jp[dex.INDEX_MCP, 0]) < 1e-9                        # in the palm plane
        assert np.sign(jp[dex.INDEX_MCP, 1]) == (1 if handedness == "right" else -1)


def test_dex_retargeting_input_is_independent_of_the_camera_and_mirrors_with_the_hand():
    (hand,) = known_hands("right", 1)
    xyz = hand["xyz"].astype(np.float64)
    rng = np.random.default_rng(0)
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R *= np.sign(np.linalg.det(R))                                      # a proper rotation
    moved = xyz @ R.T + [0.3, -0.1, 0.2]
    np.testing.assert_allclose(dex.retargeting_joint_pos(moved, "right"), dex.retargeting_joint_pos(xyz, "right"),
                               atol=1e-9)
    # the same hand's mirror image, as a left hand: the same joint_pos with y negated
    left = dex.retargeting_joint_pos(mirror_points(xyz), "left")
    np.testing.assert_allclose(left, dex.retargeting_joint_pos(xyz, "right") * [1, -1, 1], atol=1e-9)


def test_ref_value_as_dex_retargetings_examples_form_it():
    (hand,) = known_hands("right", 1)
    jp = dex.retargeting_joint_pos(hand["xyz"], "right")
    tips = [4, 8, 12, 16, 20]                                           # MediaPipe: thumb .. little tip
    vectors = dex.ref_value(jp, [[0] * 5, tips], "VECTOR")
    np.testing.assert_allclose(vectors, jp[tips])
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1),
                               np.linalg.norm(hand["xyz"][tips] - hand["xyz"][0], axis=1), atol=1e-6)
    np.testing.assert_allclose(dex.ref_value(jp, tips, "POSITION"), jp[tips])


def test_the_subscriber_without_a_graph_says_so(tmp_path):
    out = subprocess.run([sys.executable, str(EXAMPLES / "subscribe_pose.py")], capture_output=True, text=True,
                         timeout=30, env={**__import__("os").environ, "HANDMOCAP_RUN_DIR": str(tmp_path)})
    assert out.returncode == 1 and "no ik node runs in" in out.stderr and "Traceback" not in out.stderr
