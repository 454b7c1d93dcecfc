"""Drill: a live graph with keep-all subscribers 10x slower than the camera, for minutes.

The demo clip (640x480, 30 fps) is replayed in a loop for `--minutes` through the live graph
(replay -> detector (latest) -> shape -> ik) with the recorder (lossless: the bag must be
complete) and two keep-all consumers that take 333 ms a message, 10x slower than the frames:
one of /camera/image (raw 640x480 frames, 0.9 MB each), one of /hand/pose. With `--graph
recorder` only replay, recorder and the slow image consumer run (the recorder's memory over
an hour, cheaply).

Every 10 s it samples the resident memory (VmRSS) of every node process. Printed: per process,
while the source runs, the RSS after the first minute, the largest, the last, and the slope
over the second half (MB/min); per slow consumer the messages taken and those it was told it lost (bus queue:
handmocap.runtime.bus, Queues); the bag: messages per topic and whether every topic's
sequence numbers run without a gap from 0 to the last one its publisher sent. Writes
memory.csv and memory.png to --out.

    python benchmarks/drill_slow_subscriber.py [--minutes 10] [--graph full|recorder] [--out DIR]
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from handmocap.runtime import bus, codec  # noqa: E402
from handmocap.runtime.bag import iter_messages  # noqa: E402

CLIP = ROOT / "data" / "demo" / "hand_clip.mp4"
SLOW_S = 10 / 30          # a message takes the consumer 10 frame periods
SAMPLE_S = 10.0


def launch_file(out: Path, minutes: float, graph: str) -> Path:
    sink = lambda name, topic: (f"  {name}: {{node: graphnodes.sink, params: {{topic: {topic}, mode: all, "
                                f"work_s: {SLOW_S:.4f}, out: {out / (name + '.json')}}}}}\n")
    text = ("nodes:\n"
            f"  replay: {{node: replay, params: {{source: {CLIP}, loop: true, duration: {minutes * 60:.0f}}}, "
            "required: true}\n"
            f"  recorder: {{node: recorder, params: {{output: {out / 'drill.mcap'}, overwrite: true}}, required: true}}\n"
            + sink("slow_images", "/camera/image"))
    if graph == "full":
        text += ("  detector: {node: detector}\n  shape: {node: shape}\n  ik: {node: ik}\n"
                 + sink("slow_poses", "/hand/pose"))
    path = out / "drill.yaml"
    path.write_text(text)
    return path


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def bag_check(path: Path) -> dict:
    """topic -> (messages, seqs gap-free from 0)."""
    seqs: dict[str, list] = {}
    for topic, type_name, payload, _ in iter_messages(path):
        seqs.setdefault(topic, []).append(codec.decode(payload, type_name)["header"]["seq"])
    return {t: (len(s), sorted(s) == list(range(len(s)))) for t, s in seqs.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--graph", choices=("full", "recorder"), default="full")
    ap.add_argument("--out", type=Path, default=None, help="folder for the bag, memory.csv and memory.png "
                    "(default: a temporary one, removed)")
    args = ap.parse_args()
    keep = args.out is not None
    out = (args.out or Path(tempfile.mkdtemp(prefix="drill-"))).resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_dir = Path(tempfile.mkdtemp(prefix="hm-drill-"))
    env = {**os.environ, "HANDMOCAP_RUN_DIR": str(run_dir),
           "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    lf = launch_file(out, args.minutes, args.graph)
    print(f"drill: {args.graph} graph, {args.minutes:g} min, consumers at {SLOW_S * 1000:.0f} ms/message, "
          f"queues {bus.QUEUE_MESSAGES} + {bus.QUEUE_MESSAGES} frames, {bus.QUEUE_MESSAGES_SMALL} + "
          f"{bus.QUEUE_MESSAGES_SMALL} other messages; RSS every {SAMPLE_S:.0f} s", flush=True)
    log = open(out / "handlaunch.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=env,
                            stdout=log, stderr=subprocess.STDOUT, text=True)
    samples: list[tuple[float, str, float]] = []   # (minutes since start, process, RSS MB)
    t0 = time.monotonic()
    pids: dict[str, int] = {"handlaunch": proc.pid}
    while proc.poll() is None:
        time.sleep(1.0)
        if (time.monotonic() - t0) // SAMPLE_S == (time.monotonic() - t0 - 1.0) // SAMPLE_S:
            continue
        for info in bus.read_node_files(run_dir).values():
            pids[info.name] = info.pid
        minute = (time.monotonic() - t0) / 60
        for name, pid in pids.items():
            mb = rss_mb(pid)
            if mb is not None:
                samples.append((minute, name, mb))
        last = {n: mb for m, n, mb in samples if m == minute}
        print(f"  {minute:5.1f} min  " + "  ".join(f"{n} {mb:.0f}" for n, mb in sorted(last.items())) + "  MB",
              flush=True)
    log.close()
    text = (out / "handlaunch.log").read_text()
    print(f"handlaunch exit {proc.returncode}")

    with open(out / "memory.csv", "w", newline="") as f:
        csv.writer(f).writerows([("minute", "process", "rss_mb"), *samples])
    print(f"\n{'process':14s} {'RSS@1min':>9s} {'max':>7s} {'last':>7s} {'slope 2nd half':>15s}")
    bounded = True
    running = [s for s in samples if s[0] <= args.minutes]   # while the source ran (not the drain after it)
    for name in sorted({n for _, n, _ in running}):
        t = np.array([m for m, n, _ in running if n == name])
        mb = np.array([v for _, n, v in running if n == name])
        after = mb[t >= 1.0] if (t >= 1.0).any() else mb
        half = t >= t[-1] / 2
        slope = np.polyfit(t[half], mb[half], 1)[0] if half.sum() >= 3 else float("nan")
        print(f"{name:14s} {after[0]:8.0f}M {mb.max():6.0f}M {mb[-1]:6.0f}M {slope:+11.2f} MB/min")
        bounded &= bool(after.max() - after[0] < 100)
    for name in ("slow_images", "slow_poses"):
        f = out / f"{name}.json"
        if f.exists():
            seen = json.loads(f.read_text())
            s = np.array(seen["seqs"])
            print(f"{name}: took {len(s)} messages in order: {bool((np.diff(s) > 0).all())}, told it lost "
                  f"{seen['lost']}; taken + lost = {len(s) + seen['lost']} (highest seq taken + 1 = "
                  f"{'?' if not len(s) else int(s.max()) + 1} or more)")
    replayed = re.search(r"replayed (\d+) frame", text)
    checks = bag_check(out / "drill.mcap")
    print("bag: " + ", ".join(f"{t} {n}{'' if ok else ' (GAPS)'}" for t, (n, ok) in sorted(checks.items())))
    complete = all(ok for _, ok in checks.values()) and replayed is not None \
        and checks.get("/camera/image", (0, False))[0] == int(replayed.group(1))
    print(f"replay sent {replayed.group(1) if replayed else '?'} frames; bag complete: {complete}; "
          f"memory bounded (each process within 100 MB of its RSS at 1 min): {bounded}")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for name in sorted({n for _, n, _ in samples}):
            ax.plot([m for m, n, _ in samples if n == name], [v for _, n, v in samples if n == name], label=name)
        ax.set(xlabel="minutes", ylabel="RSS (MB)", title=f"drill_slow_subscriber ({args.graph}, "
               f"consumers {SLOW_S * 1000:.0f} ms/message)")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "memory.png", dpi=100)
    except ImportError:
        pass
    if keep:
        print(f"wrote {out}/memory.csv, memory.png, drill.mcap, handlaunch.log")
    else:
        import shutil
        shutil.rmtree(out)
    return 0 if (proc.returncode == 0 and complete and bounded) else 1


if __name__ == "__main__":
    sys.exit(main())
