"""The retarget node: dex-retargeting drives the project's own toy robot hand
(examples/robot_hand) from /hand/pose, offline and in a launched teleop graph."""
import importlib.util

import numpy as np
import pytest

from conftest import DEMO_CLIP, ROOT, handlaunch
from handmocap.runtime import codec
from handmocap.runtime.bag import iter_messages
from handmocap.perception.hand_model import HandModel
from handmocap.perception.pose import surest_per_side

pytestmark = pytest.mark.skipif(importlib.util.find_spec("dex_retargeting") is None,
                                reason="dex-retargeting not installed (pip install -e '.[retarget]')")
TOY = ROOT / "examples" / "robot_hand" / "toy_hand_right.yml"
MODEL = HandModel.load()


def posed(curl):
    """Joints (21,3) m of the average right hand with every finger joint bent by `curl` rad."""
    pose = np.zeros((16, 3))
    pose[1:, 2] = curl
    return MODEL.forward(pose)[1]


def test_robot_follows_the_hand_open_and_closed():
    from handmocap.perception.retarget import RobotHand
    robot = RobotHand(TOY)
    assert robot.joint_names == ["index_mcp", "index_pip", "middle_mcp", "middle_pip", "thumb_mcp", "thumb_ip"]
    settle = lambda xyz, side="right": [robot.retarget(xyz, side) for _ in range(20)][-1]
    open_q, fist_q = settle(posed(0.0)), settle(posed(1.0))
    assert np.all(fist_q[:4] > open_q[:4] + 0.5)              # the fingers close with the hand
    assert np.all(np.abs(open_q[:4]) < 0.7)                   # an open hand leaves them open
    # a left hand is read in its own (mirrored) frame: its mirror image moves the robot alike
    left = settle(posed(1.0) * [-1, 1, 1], "left")
    np.testing.assert_allclose(left, fist_q, atol=0.05)


def test_a_missing_config_urdf_or_library_is_one_clear_error():
    from handmocap.nodes import retarget
    with pytest.raises(ValueError, match="at least one side"):
        retarget.check_params({"right": None, "left": None})
    with pytest.raises(ValueError, match="no such file"):
        retarget.check_params({"right": "nowhere/robot.yml"})
    with pytest.raises(ValueError, match="urdf_dir: no such folder"):
        retarget.check_params({"right": str(TOY), "urdf_dir": "/nonexistent"})
    for bad in (-0.1, 1.5, "high"):
        with pytest.raises(ValueError, match="min_confidence"):
            retarget.check_params({"right": str(TOY), "min_confidence": bad})
    from handmocap.perception.retarget import RobotHand
    with pytest.raises(FileNotFoundError, match="allegro_hand_right"):
        RobotHand("no_such_robot")


def test_teleop_graph_retargets_every_pose(tmp_path):
    """launch/teleop.yaml on a recorded clip: one /robot/joint_states per /hand/pose, stamped
    alike, equal to the same robot run offline on the recorded poses (without the time budget,
    whose cut depends on the machine's load)."""
    bag = tmp_path / "teleop.mcap"
    out = handlaunch([ROOT / "launch" / "teleop.yaml", f"device:={DEMO_CLIP}", f"bag:={bag}", f"right:={TOY}",
                      f"left:={TOY}", "max_ms:=null"], tmp_path / "run", timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    read = lambda topic: [codec.decode(payload, kind) for _, kind, payload, _ in iter_messages(bag, [topic])]
    poses, robots = read("/hand/pose"), read("/robot/joint_states")
    assert len(poses) >= 60 and len(robots) == len(poses)
    assert [m["header"]["stamp_ns"] for m in robots] == [m["header"]["stamp_ns"] for m in poses]
    from handmocap.perception.retarget import RobotHand
    offline = {side: RobotHand(TOY) for side in ("right", "left")}
    moved = 0
    for pose, robot in zip(poses, robots):
        sides = {h["handedness"] for h in pose["hands"]}
        assert {r["handedness"] for r in robot["robots"]} == sides
        for r in robot["robots"]:
            hand = surest_per_side(pose["hands"])[r["handedness"]]
            expected = offline[r["handedness"]].retarget(hand["xyz"], r["handedness"])
            np.testing.assert_allclose(r["position"], expected, atol=1e-6)
            assert r["name"] == offline["right"].joint_names and r["track_id"] == hand["track_id"]
            moved += 1
    assert moved >= 60


def test_the_surer_hand_moves_the_robot_and_an_unsure_one_leaves_it():
    """Of two right hands the one with the higher mean joint confidence is retargeted (not
    the presence score, which is 1.0 on most hands); with min_confidence a hand below it
    leaves its side out of the message (the robot holds its last command); a HandPose
    recorded before `confidence` existed is ranked by its score."""
    from handmocap.nodes import retarget
    from handmocap.perception.retarget import RobotHand
    hand = lambda tid, curl, peaks, side="right": {  # noqa: E731
        "track_id": tid, "handedness": side, "score": 1.0, "xyz": posed(curl), "quat": np.tile([1.0, 0, 0, 0], (21, 1)),
        "confidence": np.full(21, peaks, np.float32)}
    robots, names = {"right": RobotHand(TOY)}, {"right": "toy"}
    sure, unsure = hand(3, 1.0, 0.8), hand(7, 0.0, 0.3)
    body = retarget.robots_message(robots, names, [unsure, sure])
    assert [r["track_id"] for r in body["robots"]] == [3]
    assert retarget.robots_message(robots, names, [unsure], min_confidence=0.5)["robots"] == []
    assert [r["track_id"] for r in retarget.robots_message(robots, names, [unsure, sure], 0.5)["robots"]] == [3]
    old = [{k: v for k, v in h.items() if k != "confidence"} for h in (unsure, sure)]
    old[0]["score"], old[1]["score"] = 0.9, 0.6
    assert [r["track_id"] for r in retarget.robots_message(robots, names, old)["robots"]] == [7]
    bad = hand(9, 0.5, 0.9)
    bad["xyz"] = np.full((21, 3), np.nan)
    assert [r["track_id"] for r in retarget.robots_message(robots, names, [bad, unsure])["robots"]] == [7]
