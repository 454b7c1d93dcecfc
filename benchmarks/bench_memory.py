"""The graph's memory against MediaPipe's, on the same clip at 30 fps: PSS and RSS per process.

    python benchmarks/bench_memory.py [--video V] [--frames 300] [--max-hands 2] [--record-all]

Ours: the product's graph as benchmarks/bench_e2e.py launches it (replay at rate 1 in the
perception container with detector, shape and ik; the recorder a process of its own), the
launcher included. MediaPipe Hands 0.10.21 (legacy solution, tracking mode, the same
max_num_hands) fed the same frames on a 30 fps clock in one process, each decoded when due
(scripts/mediapipe_reference.py --paced --stream; its venv found or built as bench_tracker.py does).
Every SAMPLE_S each process's PSS (its private pages plus its share of the pages it shares:
the libraries every process of the graph maps count once in the sum) and RSS are read from
/proc/PID/smaps_rollup; printed: the sample where the sum over the graph's processes was
largest, process by process (MediaPipe's likewise). Default clip: the data pack's two-hand clip (bench_tracker.REAL_CLIPS),
else the demo clip.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_e2e import chain_yaml, graph_env  # noqa: E402
from bench_tail import clip_of  # noqa: E402
from bench_tracker import ROOT, default_videos  # noqa: E402
from handmocap.training.eval_cli import reference_python  # noqa: E402

SAMPLE_S = 0.25


def memory_mb(pid: int) -> tuple[float, float] | None:
    """(PSS, RSS) MB of a process, or None once it is gone."""
    try:
        fields = dict(line.split()[:2] for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:])
    except (OSError, ValueError):
        return None
    return int(fields["Pss:"]) / 1024, int(fields["Rss:"]) / 1024


def descendants(root: int) -> list[int]:
    """root and every process below it."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo += children.get(pid, [])
    return out


def process_name(pid: int) -> str:
    """What a process is: a container (named by HANDMOCAP_CONTAINER), a node's module, or its script."""
    try:
        words = [a.decode(errors="replace") for a in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0") if a]
        env = dict(e.split(b"=", 1) for e in Path(f"/proc/{pid}/environ").read_bytes().split(b"\0") if b"=" in e)
    except OSError:
        return str(pid)
    if "--container" in words:
        import json
        members = json.loads(env.get(b"HANDMOCAP_CONTAINER", b"[]"))
        return f"container of {', '.join(m['name'] for m in members)}"
    if "-m" in words and words.index("-m") + 1 < len(words):
        return words[words.index("-m") + 1]
    scripts = [w for w in words[1:] if w.endswith(".py")]
    return Path(scripts[0]).name if scripts else Path(words[0]).name if words else str(pid)


def sampled(cmd: list[str], env: dict | None = None) -> tuple[dict, float]:
    """Run cmd to its end, sampling its processes: ({name: (PSS, RSS)} at the sample where their
    PSS sum was largest, that sum). (A process that lives a moment, such as handlaunch's forked
    checker at the start, counts only if it is there at that sample.)"""
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak: dict[str, tuple[float, float]] = {}
    total = 0.0
    while proc.poll() is None:
        now: dict[str, tuple[float, float]] = {}
        for pid in descendants(proc.pid):
            mem = memory_mb(pid)
            if mem is not None:
                name = process_name(pid)
                old = now.get(name, (0.0, 0.0))
                now[name] = (old[0] + mem[0], old[1] + mem[1])
        if sum(pss for pss, _ in now.values()) > total:
            peak, total = now, sum(pss for pss, _ in now.values())
        time.sleep(SAMPLE_S)
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd[:3])} ... failed: {proc.stderr.read()[-400:]}")
    return peak, total


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--video", type=Path, default=None)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--max-hands", type=int, default=2)
    p.add_argument("--record-all", action="store_true", help="the recorder records every topic (JPEG frames)")
    args = p.parse_args()
    video = args.video or default_videos()[-1]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        clip = clip_of(video, args.frames, tmp)
        (tmp / "graph.yaml").write_text(chain_yaml(clip, tmp / "out.mcap", 1, args.record_all, args.max_hands))
        env = graph_env(tempfile.mkdtemp(prefix="hmm", dir=tmp))
        ours, ours_total = sampled([sys.executable, "-m", "handmocap.runtime.launch", str(tmp / "graph.yaml")], env)
        python = reference_python()
        theirs, theirs_total = (sampled([str(python), str(ROOT / "scripts" / "mediapipe_reference.py"), "--bench",
                                         str(clip), "--paced", "30", "--stream", "--frames", str(args.frames),
                                         "--max-hands", str(args.max_hands)]) if python else ({}, float("nan")))
    print(f"{video.name}, {args.frames} frames at 30 fps, max hands {args.max_hands}"
          + (", every topic recorded" if args.record_all else ""))
    print("| process | PSS, MB | RSS, MB |\n|---|---|---|")
    for side, peak in (("graph", ours), ("MediaPipe", theirs)):
        for name, (pss, rss) in sorted(peak.items(), key=lambda kv: -kv[1][0]):
            print(f"| {side}: {name} | {pss:.0f} | {rss:.0f} |")
    print(f"| **graph, all its processes** | **{ours_total:.0f}** | |")
    print(f"| **MediaPipe, all its processes** | **{theirs_total:.0f}** | |")
    print(f"graph / MediaPipe PSS: {ours_total / theirs_total:.2f}")


if __name__ == "__main__":
    main()
