"""Hands live on ROS 2: latency from a ROS 2 camera image's stamp to its hands on ROS 2, beside
the same graph's /hand/pose latency, and what the ros2 node costs a frame.

    python benchmarks/bench_ros2.py [--clip PATH] [--frames 300] [--rounds 2]

Per round, in a fresh ROS_DOMAIN_ID: examples/ros2_listen_hands.py (a plain rclpy subscriber),
launch/ros2.yaml as it ships (camera taken as its driver publishes it, latest-only detector: live settings) with
bag:= recording /hand/pose, and, once the listener has found the ros2 node's publisher (DDS
discovery takes 0.1-2 s), examples/ros2_publish_video.py playing the clip at 30 fps
(sensor_msgs/Image bgr8 + CameraInfo, stamped at publish, as a driver stamps at capture).
- ROS 2 hands: the listener's receipt of /hand_<side>/joint_states - the image's ROS stamp.
- /hand/pose: the recorder's MCAP log time - the same stamp (the graph carries it).
p50/p95/max over the frames after the first second (start-up left out), and the frames that
got a pose of those sent (latest-only drops frames when the graph is behind, as live).
The ros2 node's CPU per input is its own closing log line (thread time around convert and
publish). Last, what a posed-mesh Marker would cost a hand (why the node sends the skeleton
only). Default clip: a stranger's webcam clip from ../shared (352x640), else the demo clip.
"""
import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
REAL = ROOT.parent / "shared" / "data" / "video" / "webcam" / "alimostafa_hand.mp4"
DEMO = ROOT / "data" / "demo" / "hand_clip.mp4"
WARMUP_FRAMES = 30


def run_round(clip, frames, domain, tmp):
    from conftest import read_bag
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "HANDMOCAP_RUN_DIR": tempfile.mkdtemp(prefix="hmb")}
    listener = subprocess.Popen([sys.executable, str(ROOT / "examples" / "ros2_listen_hands.py"), "--jsonl",
                                 str(tmp / "hands.jsonl"), "--seconds", "600"], env=env, stderr=subprocess.PIPE, text=True)
    listener.stderr.readline()
    graph = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(ROOT / "launch" / "ros2.yaml"),
                              "timeout_s:=3", f"bag:={tmp / 'run.mcap'}"], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    while "matched" not in listener.stderr.readline():    # DDS discovery (0.1-2 s) done before the first frame
        pass
    subprocess.run([sys.executable, str(ROOT / "examples" / "ros2_publish_video.py"), str(clip), "--frames", str(frames),
                    "--stamps", str(tmp / "stamps.txt")], env=env, check=True, capture_output=True)
    out, _ = graph.communicate(timeout=300)
    time.sleep(1.0)
    listener.terminate()
    listener.wait(timeout=20)
    if graph.returncode != 0:
        raise SystemExit(f"the graph failed:\n{out}")
    sent = [int(s) for s in (tmp / "stamps.txt").read_text().split()]
    first = sent[0] + WARMUP_FRAMES * 33_333_333
    pose = {m["header"]["stamp_ns"]: log for m, log in read_bag(tmp / "run.mcap")["/hand/pose"]}
    ros = {}
    for line in (tmp / "hands.jsonl").read_text().splitlines():
        m = json.loads(line)
        if m["topic"].endswith("joint_states"):
            ros[m["stamp_ns"]] = min(ros.get(m["stamp_ns"], np.inf), m["received_ns"])
    cpu = re.search(r"\[ros2\] INFO ros2: \d+ ROS 2 messages published; CPU (.*)", out)
    return {"sent": len(sent), "posed": len(pose), "ros_hands": len(ros),
            "pose_ms": [(log - s) / 1e6 for s, log in pose.items() if s >= first],
            "ros_ms": [(t - s) / 1e6 for s, t in ros.items() if s >= first],
            "cpu": cpu.group(1) if cpu else "?"}


def mesh_marker_ms(repeats=10):
    """What a posed-mesh Marker (TRIANGLE_LIST of the hand model's faces) would cost the ros2
    node a hand: built as rosbags objects and serialized as the skeleton markers are -> (ms, bytes)."""
    from handmocap.perception.hand_model import HandModel
    from handmocap.interop.ros2_messages import Ros2Messages, typestore
    model, ts = HandModel.load(), typestore()
    build = Ros2Messages(ts)
    corners = np.random.default_rng(0).random((model.faces.size, 3))      # one point per triangle corner
    t0 = time.perf_counter()
    for _ in range(repeats):
        marker = build.markers({"right": {"xyz": np.zeros((21, 3))}}, 0, "camera_optical_frame")
        marker.markers[0].points = [build.point(p) for p in corners]
        raw = ts.serialize_cdr(marker, "visualization_msgs/msg/MarkerArray")
    return (time.perf_counter() - t0) / repeats * 1e3, len(raw)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clip", type=Path, default=REAL if REAL.exists() else DEMO)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--rounds", type=int, default=2)
    args = p.parse_args()
    print(f"clip {args.clip}, {args.frames} frames at 30 fps, {args.rounds} round(s)")
    pose_ms, ros_ms = [], []
    for r in range(args.rounds):
        with tempfile.TemporaryDirectory() as d:
            res = run_round(args.clip, args.frames, 30 + (os.getpid() + r) % 60, Path(d))
        pose_ms += res["pose_ms"]
        ros_ms += res["ros_ms"]
        print(f"round {r + 1}: {res['sent']} frames sent, {res['posed']} posed, {res['ros_hands']} with hands on "
              f"ROS 2; ros2 node CPU: {res['cpu']}")
    print(f"\n{'capture stamp ->':24s} {'p50 ms':>8s} {'p95 ms':>8s} {'max ms':>8s} {'frames':>7s}")
    for name, v in (("/hand/pose (graph bus)", pose_ms), ("hands on ROS 2", ros_ms)):
        v = np.asarray(v)
        print(f"{name:24s} {np.percentile(v, 50):8.1f} {np.percentile(v, 95):8.1f} {v.max():8.1f} {len(v):7d}")
    ms, size = mesh_marker_ms()
    print(f"\na posed-mesh marker (not published): {ms:.1f} ms CPU and {size / 1e3:.0f} kB a hand")


if __name__ == "__main__":
    main()
