"""How long a killed perception container leaves a live graph without poses.

    python benchmarks/drill_respawn.py [--delays 1.0 0.1] [--rounds 2] [--clip VIDEO]

The product's layout (source, detector, shape and ik in container `perception`, the recorder
a process of its own), the clip replayed at 30 fps in a loop. After 60 poses the container
is SIGKILLed; handlaunch respawns it after `respawn_delay`. Read from the bag afterwards:
- gap: from the last pose before the kill to the first one after it (what a robot feels);
- and how that splits: kill -> the new process exists (respawn delay, fork), -> the new
  process has written its node file (imports, models loaded, sockets bound), -> first pose.
Prints one row per delay and round. A respawned replay goes on where it stopped, so the
poses after the gap are of the frames that follow.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEMO_CLIP = ROOT / "data" / "demo" / "hand_clip.mp4"


def graph(clip: Path, bag: Path, delay: float) -> str:
    c = f", container: perception, respawn: true, respawn_delay: {delay}"
    return f"""
nodes:
  replay: {{node: replay, params: {{source: "{clip}", rate: 1.0, loop: true}}, required: true{c}}}
  detector: {{node: detector{c}}}
  shape: {{node: shape{c}}}
  ik: {{node: ik{c}}}
  recorder: {{node: recorder, params: {{output: "{bag}", overwrite: true}}, required: true}}
"""


def node_file(run_dir: Path, name: str) -> dict:
    try:
        return json.loads((run_dir / f"{name}.json").read_text())
    except (OSError, ValueError):
        return {}


def published(run_dir: Path, name: str, topic: str) -> int:
    stats = node_file(run_dir, name).get("stats") or {}
    return stats.get("published", {}).get(topic, 0)


def wait(what, predicate, timeout_s=60.0, step=0.005):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(step)
    raise TimeoutError(f"no {what} within {timeout_s} s")


def kill_container(run_dir: Path) -> tuple[int, int]:
    """SIGKILL the perception container (the process ik's node file names): (its pid, the time ns)."""
    pid, when = node_file(run_dir, "ik")["pid"], time.time_ns()
    os.kill(pid, signal.SIGKILL)
    return pid, when


def one_round(clip: Path, delay: float, work: Path) -> dict:
    """Run the graph, kill the container once; the figures of this round (seconds)."""
    from handmocap.runtime import codec
    from handmocap.runtime.bag import iter_messages
    bag, run_dir = work / "o.mcap", work / "run"
    lf = work / "g.yaml"
    lf.write_text(graph(clip, bag, delay))
    env = {**os.environ, "HANDMOCAP_RUN_DIR": str(run_dir)}
    proc = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait("60 poses", lambda: published(run_dir, "ik", "/hand/pose") >= 60)
        victim, kill_ns = kill_container(run_dir)
        # the new process: its pid in the node file (written once its nodes are up)
        wait("a new container", lambda: node_file(run_dir, "ik").get("pid") not in (None, victim))
        up_ns = time.time_ns()
        wait("60 poses after the respawn", lambda: published(run_dir, "ik", "/hand/pose") >= 60, step=0.05)
        os.kill(node_file(run_dir, "replay")["pid"], signal.SIGTERM)   # ends the source, and so the graph
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.communicate(timeout=30)
    received = np.array([log_ns for topic, _, _, log_ns in iter_messages(bag, ["/hand/pose"])])
    stamps = np.array([codec.decode(p, t)["header"]["stamp_ns"] for _, t, p, _ in iter_messages(bag, ["/hand/pose"])])
    before, after = received[received < kill_ns], received[received > kill_ns]
    first_after = after.min()
    return {"gap_s": (first_after - before.max()) / 1e9, "kill_to_node_file_s": (up_ns - kill_ns) / 1e9,
            "kill_to_first_pose_s": (first_after - kill_ns) / 1e9,
            "first_pose_latency_ms": (first_after - stamps[received == first_after][0]) / 1e6}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--delays", type=float, nargs="+", default=[1.0, 0.1],
                   help="respawn_delay values to measure, s (default: 1.0, the launcher's default, and 0.1)")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--clip", type=Path, default=DEMO_CLIP)
    args = p.parse_args()
    print("| respawn_delay s | round | poses' gap s | kill -> new node file s | kill -> first pose s |")
    print("|---|---|---|---|---|")
    for r in range(args.rounds):
        for delay in args.delays:
            with tempfile.TemporaryDirectory() as work:
                f = one_round(args.clip, delay, Path(work))
            print(f"| {delay} | {r} | {f['gap_s']:.2f} | {f['kill_to_node_file_s']:.2f} | "
                  f"{f['kill_to_first_pose_s']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
