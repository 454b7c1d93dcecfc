"""A long run of the product's graph: is every frame recorded, and does any process grow?

    python benchmarks/soak.py [--minutes 30] [--clip VIDEO] [--every-s 10] [--csv OUT.csv]

The product's layout (replay in the perception container with detector, shape and ik; the
recorder a process of its own, recording every topic as `bag:=` does), the clip replayed at
30 fps in a loop for `--minutes`. Every `--every-s` seconds each process's resident memory
(VmRSS, /proc) is sampled. At the end: frames the source sent (its heartbeat's count) against
/camera/image messages in the bag, poses in the bag, and per process its RSS at 1 minute, at
the end, the largest, and its growth after the first minute (the curve to --csv). Default
clip: the data pack's one-hand real clip, else the demo clip.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from drill_slow_subscriber import rss_mb  # noqa: E402  (VmRSS of a process, MB)

REAL_CLIP = ROOT.parent / "shared" / "data" / "video" / "webcam" / "lujunwang_hand.mp4"
DEMO_CLIP = ROOT / "data" / "demo" / "hand_clip.mp4"


def node_files(run_dir: Path) -> dict:
    out = {}
    for f in run_dir.glob("*.json"):
        try:
            out[f.stem] = json.loads(f.read_text())
        except (OSError, ValueError):
            pass
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--clip", type=Path, default=REAL_CLIP if REAL_CLIP.is_file() else DEMO_CLIP)
    p.add_argument("--every-s", type=float, default=10.0)
    p.add_argument("--csv", type=Path, help="write the RSS samples (s, process, MB) here")
    args = p.parse_args()
    from handmocap.runtime.bag import iter_messages
    with tempfile.TemporaryDirectory() as work:
        work = Path(work)
        bag, run_dir, lf = work / "soak.mcap", work / "run", work / "soak.yaml"
        c = ", container: perception"
        lf.write_text(f"""
nodes:
  replay: {{node: replay, params: {{source: "{args.clip}", rate: 1.0, loop: true}}, required: true{c}}}
  detector: {{node: detector, required: true{c}}}
  shape: {{node: shape{c}}}
  ik: {{node: ik, required: true{c}}}
  recorder: {{node: recorder, params: {{output: "{bag}", overwrite: true}}, required: true}}
""")
        env = {**os.environ, "HANDMOCAP_RUN_DIR": str(run_dir)}
        proc = subprocess.Popen([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        samples, sent = [], 0
        t0 = time.monotonic()
        try:
            while time.monotonic() - t0 < 60 * args.minutes:
                time.sleep(args.every_s)
                files = node_files(run_dir)
                pids = {"launcher": proc.pid, "perception": files.get("ik", {}).get("pid"),
                        "recorder": files.get("recorder", {}).get("pid")}
                t = time.monotonic() - t0
                for name, pid in pids.items():
                    mb = rss_mb(pid) if pid else None
                    if mb is not None:
                        samples.append((t, name, mb))
                sent = (files.get("replay", {}).get("stats") or {}).get("published", {}).get("/camera/image", sent)
                print(f"{t / 60:5.1f} min: " + ", ".join(f"{n} {m:.0f} MB" for tt, n, m in samples if tt == t) +
                      f"; {sent} frames sent", flush=True)
            # end the source: its end-of-stream drains the graph; it logs how many frames it sent
            os.kill(node_files(run_dir)["replay"]["pid"], signal.SIGTERM)
            out, _ = proc.communicate(timeout=120)
            said = re.search(r"replayed (\d+) frame", out)
            sent = int(said.group(1)) if said else None
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                proc.communicate(timeout=60)
        counts = {}
        for topic, _, _, _ in iter_messages(bag):
            counts[topic] = counts.get(topic, 0) + 1
    print(f"\nframes the source sent (its closing line): {sent}; "
          f"in the bag: /camera/image {counts.get('/camera/image', 0)}, /hand/pose {counts.get('/hand/pose', 0)}")
    print("\n| process | RSS at 1 min, MB | at the end | largest | growth after 1 min |\n|---|---|---|---|---|")
    for name in ("launcher", "perception", "recorder"):
        s = [(t, m) for t, n, m in samples if n == name]
        if not s:
            continue
        after = [m for t, m in s if t >= 60] or [s[-1][1]]
        print(f"| {name} | {after[0]:.1f} | {s[-1][1]:.1f} | {max(m for _, m in s):.1f} | {s[-1][1] - after[0]:+.1f} |")
    if args.csv:
        args.csv.write_text("s,process,rss_mb\n" + "".join(f"{t:.0f},{n},{m:.1f}\n" for t, n, m in samples))


if __name__ == "__main__":
    main()
