"""retarget: robot hands that follow the tracked hands. /hand/pose -> /robot/joint_states.

A thin loop over handmocap.perception.retarget.RobotHand (dex-retargeting; the `retarget` extra). One
robot per side, each its own dex-retargeting config and URDF, as the launch file names them:

    retarget:
      node: retarget
      params: {right: allegro_hand_right, left: allegro_hand_left, urdf_dir: ~/dex-urdf/robots/hands}

Params: right, left: a dex-retargeting config (.yml path, or the name of one bundled with
dex-retargeting, e.g. allegro_hand_right; null: no robot for that side; at least one);
urdf_dir: the folder the configs' urdf_path is relative to (null: each config's own folder);
max_ms: the time budget of one hand's optimisation (dex-retargeting's nlopt stops there with
its best so far; null: until it converges): 4 ms keeps the added latency p95 under 5 ms per
hand on Allegro and Inspire (benchmarks/bench_retarget.py);
min_confidence: a hand whose mean joint confidence (pose.hand_certainty) is below this does
not move its robot, which holds its last command (null: every hand moves it; what a
threshold keeps and how far off those hands are: README, "Using /hand/pose").
Every /hand/pose gets one /robot/joint_states message (the robots of the sides in view; of two
hands of one side the surer one), stamped with the frame's capture time.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Callable

from handmocap.runtime.node import Message, Node, check_number_param, run, spin
from handmocap.perception.pose import hand_certainty, surest_per_side
from handmocap.perception.retarget import RobotHand

PARAMS = {"right": None, "left": None, "urdf_dir": None, "max_ms": 4.0, "min_confidence": None}
SIDES = ("right", "left")


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param)."""
    if importlib.util.find_spec("dex_retargeting") is None:
        raise ValueError("retarget: dex-retargeting is not installed: pip install -e '.[retarget]'")
    if not any(params.get(side) for side in SIDES):
        raise ValueError("retarget params right, left: name a dex-retargeting config for at least one side")
    for side in SIDES:
        value = params.get(side)
        if value is not None and str(value).endswith((".yml", ".yaml")) and not Path(str(value)).expanduser().is_file():
            raise ValueError(f"retarget param {side}: no such file {value}")
    check_number_param("retarget", "max_ms", params.get("max_ms", PARAMS["max_ms"]), positive=True, null=True)
    min_confidence = params.get("min_confidence")
    check_number_param("retarget", "min_confidence", min_confidence, minimum=0, null=True)
    if min_confidence is not None and min_confidence > 1:
        raise ValueError(f"retarget param min_confidence: expected 0 to 1 or null, got {min_confidence}")
    urdf_dir = params.get("urdf_dir")
    if urdf_dir is not None and not Path(str(urdf_dir)).expanduser().is_dir():
        raise ValueError(f"retarget param urdf_dir: no such folder {urdf_dir}")


def robots_message(robots: dict, names: dict, hands: list[dict], min_confidence: float | None = None) -> dict:
    """The RobotJointStates body for one HandPose message's hands: per side with a robot, the
    surest hand of that side (pose.surest_per_side) retargeted, unless its hand_certainty is
    below min_confidence. robots: side -> RobotHand; names: side -> config name."""
    out = []
    surest = surest_per_side(hands)
    for side, robot in robots.items():
        hand = surest.get(side)
        if hand is not None and (min_confidence is None or hand_certainty(hand) >= min_confidence):
            out.append({"handedness": side, "track_id": int(hand["track_id"]), "robot": names[side],
                        "name": robot.joint_names, "position": robot.retarget(hand["xyz"], side)})
    return {"robots": out}


def start() -> tuple[Node, Callable[[Message], None]]:
    """The node, set up (topics, robots), and its handler of one /hand/pose message."""
    node = Node("retarget", params=PARAMS)
    p = node.params
    node.subscribe("/hand/pose", "HandPose", mode="all")       # every pose a robot command
    node.advertise("/robot/joint_states", "RobotJointStates")
    robots = {side: RobotHand(p[side], p["urdf_dir"], p["max_ms"]) for side in SIDES if p[side]}
    names = {side: Path(str(p[side])).stem for side in robots}

    def on_pose(msg: Message) -> None:
        body = robots_message(robots, names, msg.data["hands"], p["min_confidence"])
        node.publish("/robot/joint_states", body, stamp_ns=msg.stamp_ns,
                     frame_id=msg.data["header"]["frame_id"])
    return node, on_pose


def main() -> None:
    spin(start)


if __name__ == "__main__":
    run(main)
