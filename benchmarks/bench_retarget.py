"""Robot joints from /hand/pose against robot joints from MediaPipe, on dex-retargeting's own clip.

dex-retargeting (pip install -e '.[retarget]') ships its clip's MediaPipe input
(`human_joint_right.pkl`: per frame the (21,3) joint_pos its SingleHandDetector feeds to the
retargeting, metres, wrist frame). Here the same clip goes through HandTracker (the graph's
code path: detector, shape, IKNet, translation), each frame's right hand becomes joint_pos
exactly as the retarget node makes it (handmocap.perception.retarget), and both inputs drive one
dex-retargeting instance each per robot config (ours with the node's time budget max_ms). Printed per robot: the mean absolute
difference of the robot joints (rad), the median per-joint correlation over time, and the
retargeting time per call (ms, p50/p95); and the hand's wrist -> middle-knuckle length
(cm, min/median/max over frames), which sets how far the robot fingers close.

Needs the pack's video/dex_retargeting/ and robot URDFs (dex-retargeting's configs name
them relative to a URDF folder, e.g. a checkout of github.com/dexsuite/dex-urdf's
robots/hands; they are not on PyPI):

    python benchmarks/bench_retarget.py --urdf-dir PATH [--robots allegro_hand_right inspire_hand_right]
"""
from __future__ import annotations

import argparse
import importlib.util
import pickle
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.retarget import RobotHand, ref_value, retargeting_joint_pos
from handmocap.perception.tracker import HandTracker

ROOT = Path(__file__).resolve().parents[1]

CLIP = ROOT.parent / "shared" / "data" / "video" / "dex_retargeting"


def pose_xyz(video, hand_length):
    """Per frame of the clip: the right hand's /hand/pose xyz (21,3) metres, or None."""
    tracker = HandTracker(hand_length=hand_length)
    cap = cv2.VideoCapture(str(video))
    out = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        hands = [h for h in tracker.process(frame) if h["handedness"] == "right"]
        out.append(max(hands, key=lambda h: h["score"])["xyz"].astype(np.float64) if hands else None)
    return out


def retarget_all(robot: RobotHand, joint_pos_frames):
    """Robot qpos (N, J) for joint_pos (21,3) per frame (None: the last input held, as a live
    loop would), through one RobotHand (its SeqRetargeting: warm start, low-pass filter and
    time budget), and the time of each retarget() call (s)."""
    qpos, times, last = [], [], None
    for joint_pos in joint_pos_frames:
        last = joint_pos if joint_pos is not None else last
        if last is None:
            qpos.append(None)
            continue
        t0 = time.perf_counter()
        qpos.append(robot.retargeting.retarget(ref_value(last, robot.indices, robot.kind)))
        times.append(time.perf_counter() - t0)
    return qpos, np.array(times)


def compare(ours, theirs):
    """Mean |ours - theirs| (rad) over frames both have and joints, and the median over
    joints of the correlation over time (joints that stay still on either side left out)."""
    both = [(a, b) for a, b in zip(ours, theirs) if a is not None and b is not None]
    a, b = (np.array(x) for x in zip(*both))
    moving = (a.std(0) > 1e-3) & (b.std(0) > 1e-3)
    corr = [np.corrcoef(a[:, j], b[:, j])[0, 1] for j in np.flatnonzero(moving)]
    return float(np.abs(a - b).mean()), float(np.median(corr)), len(both)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--urdf-dir", type=Path, required=True, help="folder the configs' urdf_path are relative to")
    ap.add_argument("--clip", type=Path, default=CLIP, help="folder with human_hand_video.mp4 and human_joint_right.pkl")
    ap.add_argument("--robots", nargs="+", default=["allegro_hand_right", "inspire_hand_right"],
                    help="dex-retargeting teleop config names")
    ap.add_argument("--hand-length", type=float, default=None, help="metres (default: the ik node's default)")
    ap.add_argument("--max-ms", type=float, default=None,
                    help="time budget per retarget call for /hand/pose's run (default: the retarget node's)")
    args = ap.parse_args()
    if importlib.util.find_spec("dex_retargeting") is None:
        sys.exit("bench_retarget: dex-retargeting is not installed: pip install -e '.[retarget]'")
    video, reference = args.clip / "human_hand_video.mp4", args.clip / "human_joint_right.pkl"
    for path in (video, reference, args.urdf_dir):
        if not path.exists():
            sys.exit(f"bench_retarget: {path} not found")

    from handmocap.perception.pose import PoseSettings
    hand_length = PoseSettings().hand_length if args.hand_length is None else args.hand_length
    if args.max_ms is None:
        from handmocap.nodes.retarget import PARAMS
        args.max_ms = PARAMS["max_ms"]
    t0 = time.perf_counter()
    xyz = pose_xyz(video, hand_length)
    mediapipe = [np.asarray(p, np.float64) for p in pickle.load(open(reference, "rb"))]
    found = [p for p in xyz if p is not None]
    knuckle = np.array([np.linalg.norm(p[9] - p[0]) for p in found]) * 100
    print(f"clip {video.name}: {len(xyz)} frames, right hand in {len(found)} "
          f"({time.perf_counter() - t0:.0f} s); hand_length {hand_length} m")
    print(f"wrist -> middle knuckle, /hand/pose: min {knuckle.min():.2f}  median {np.median(knuckle):.2f}  "
          f"max {knuckle.max():.2f} cm; MediaPipe: median "
          f"{np.median([np.linalg.norm(p[9] - p[0]) for p in mediapipe]) * 100:.2f} cm")
    ours_pos = [None if p is None else retargeting_joint_pos(p, "right") for p in xyz]
    print(f"{'robot':24s} {'mean |dq| rad':>14s} {'median corr':>12s} {'frames':>7s} {'retarget ms p50/p95':>20s}")
    for robot in args.robots:
        ours, times = retarget_all(RobotHand(robot, args.urdf_dir, args.max_ms), ours_pos)
        theirs, _ = retarget_all(RobotHand(robot, args.urdf_dir), mediapipe)
        diff, corr, n = compare(ours, theirs)
        print(f"{robot:24s} {diff:14.3f} {corr:12.3f} {n:7d} "
              f"{np.percentile(times, 50) * 1e3:9.2f} / {np.percentile(times, 95) * 1e3:.2f}")


if __name__ == "__main__":
    main()
