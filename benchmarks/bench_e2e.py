"""The whole graph against the same pipeline in one process, on 640x480 frames of one hand.

    python benchmarks/bench_e2e.py [--frames 300] [--record-all] [--max-hands 2]
                                   [--no-container | --source-outside] [--trace]

Frames: the rendered demo clip (data/demo/hand_clip.mp4, 640x480, 30 fps, one right hand)
played forwards and backwards until `--frames` long (no jump where it repeats, so the hand
stays tracked), written once to a temporary MP4 (mp4v, as the clip itself).

Rows of the table:
- graph @30 fps: handlaunch with replay (rate 1) -> detector (every_frame: keep-all, as
  launch/demo.yaml) -> shape -> ik -> recorder of /hand/pose only (the probe: its MCAP log
  time is the receipt time; with --record-all it records every topic as the demo does).
  As in the product launch files, replay, detector, shape and ik run in one container
  process (`container: perception`: one zmq Context, inproc:// between them; the frame
  reaches the detector without a socket, and its pixels without a copy on the receiving
  side; detector, shape and ik called in turn by one executor thread, the source a thread
  of its own); the recorder is a process of its own, so the pose still crosses a
  process boundary. --source-outside: replay a process of its own, only detector, shape
  and ik in the container (the product's layout before the source joined it: the frame
  crosses a unix socket). --no-container: every node its own process. At rate 1, replay
  decodes each frame just before it is due (as a camera delivers it), not while the graph
  still works on the previous one.
  --trace: the 30 fps run with HANDMOCAP_TRACE, and the p50/p95 of each hop from the nodes'
  publish and receive times, and each thread's CPU time over the run per frame (the
  container's executor thread runs detector, shape and ik)
  (start-up and idle polling included; OpenCV's decoding threads, zmq's I/O threads and the
  heartbeats are not in any node's figure); tracing itself costs a little.
  Latency = receipt of /hand/pose - capture stamp, p50/p95 over the frames after the first
  second (the start-up transient, when 5 processes start on 2 cores, is left out and
  reported on its own line).
- graph unthrottled: the same with rate 0 (replay sends as fast as the graph takes frames:
  it decodes the next one once fewer than 3 sent frames are still queued or held).
  Throughput = /hand/pose messages per second of receipt time after the first second of
  poses; its "latency" includes up to 3 frames of queueing and is not a latency figure.
- in-process: HandTracker.process on the same decoded frames, one after the other, after
  one warm-up pass (wall and CPU time per frame).
- in-process @30 fps: the same, each frame started on a 30 fps clock as a camera delivers
  them. A process that sleeps between frames wakes with cold caches and takes longer per
  frame (here ~6.4 ms against ~4.3 back to back), and so do the graph's nodes: this row,
  not the back-to-back one, is what the graph's latency at 30 fps compares with.

Costs: graph CPU per frame = (CPU of the whole unthrottled graph over `--frames` - CPU of
the same graph over 30 frames) / (frames - 30): process start, imports and model loading
cancel out (CPU of the launcher and every node, from getrusage of reaped children). It
includes replay's video decoding, which the in-process row does not (its frames come
decoded); the decoding's own CPU time (replay's reader over the whole clip in a process of
its own, decoder threads included) is printed beside it.
Graph overhead is given four ways: latency at 30 fps (p50) - in-process at 30 fps (p50;
and, for reference, - the back-to-back median);
graph CPU per frame - in-process CPU per frame (- decoding); graph CPU per frame - the mean
CPU per frame of replay's reader and HandTracker in one process (the in-process pipeline
doing the graph's whole job, decoding included); 1000 / unthrottled frames/s - in-process
median wall time. Targets (issue 7): unthrottled >= 100 frames/s, p95 latency at 30 fps
<= 20 ms, overhead <= 2 ms per frame.

Everything runs on whatever CPU is free: note the load average printed first and last
(other training jobs share this 2-core machine).
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from handmocap.runtime.frames import read_video

ROOT = Path(__file__).resolve().parent.parent
CLIP = ROOT / "data" / "demo" / "hand_clip.mp4"
WARMUP_FRAMES = 30     # the first second at 30 fps
LAYOUTS = {"source": "replay, detector, shape, ik in one container (the product's launch files); recorder apart",
           "perception": "detector, shape, ik in one container; replay and recorder apart",
           None: "every node its own process"}


def make_clip(path: Path, n: int) -> list[np.ndarray]:
    """Write the demo clip ping-ponged to n frames at `path` (mp4v, 30 fps); return the frames
    as OpenCV decodes the written file (what replay will publish), each (480,640,3) uint8."""
    src = read_video(CLIP)
    h, w = src[0].shape[:2]
    if (w, h) != (640, 480):
        raise SystemExit(f"{CLIP} is {w}x{h}, this benchmark wants 640x480: render one with "
                         f"scripts/render_demo_clip.py")
    order = src + src[-2:0:-1]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30, (w, h))
    for i in range(n):
        writer.write(order[i % len(order)])
    writer.release()
    frames = read_video(path)
    assert len(frames) == n
    return frames


def decode_cpu_ms(path: Path) -> float:
    """CPU ms per frame that replay's reader (frames.open_frames) spends decoding `path`: the
    whole file in a fresh process, its decoder threads included, total / frames (replay pays
    it, the in-process row not). Timed per frame in this process, the figure swung between
    0.7 and 3.5 ms from run to run: it also counted OpenCV's worker threads, still busy
    after writing the clip."""
    code = ("import sys, time\n"
            "from handmocap.runtime.frames import open_frames\n"
            "frames = open_frames(sys.argv[1])\n"
            "c = time.process_time()\n"
            "n = sum(1 for _ in frames)\n"
            "print(1e3 * (time.process_time() - c) / n)\n")
    r = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    return float(r.stdout.strip().splitlines()[-1])


def in_process_with_decoding_cpu_ms(path: Path, max_hands: int) -> float:
    """Mean CPU ms per frame of replay's reader and HandTracker.process in one fresh process
    (decoder threads included), over the clip after one warm-up pass: the in-process
    pipeline doing the graph's whole job, so the graph's CPU compares with it directly,
    without subtracting a decoding time measured apart (and mean against mean: the
    in-process row is a median)."""
    code = ("import sys, time\n"
            "from handmocap.runtime.frames import open_frames\n"
            "from handmocap.perception.tracker import HandTracker\n"
            "t = HandTracker(max_hands=int(sys.argv[2]))\n"
            "for _, f in open_frames(sys.argv[1]): t.process(f)\n"
            "t.reset()\n"
            "c, n = time.process_time(), 0\n"
            "for _, f in open_frames(sys.argv[1]):\n"
            "    t.process(f)\n"
            "    n += 1\n"
            "print(1e3 * (time.process_time() - c) / n)\n")
    r = subprocess.run([sys.executable, "-c", code, str(path), str(max_hands)], capture_output=True, text=True,
                       check=True)
    return float(r.stdout.strip().splitlines()[-1])


def children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def chain_yaml(clip: Path, bag: Path, rate: float, record_all: bool, max_hands: int,
               container: str | None = "source") -> str:
    """The launch file of the measured chain: replay -> detector -> shape -> ik -> recorder of
    /hand/pose (every topic with record_all). container "source": replay, detector, shape and
    ik in one process (the product's layout); any other value: the source apart; None: none."""
    topics = "" if record_all else ", topics: [/hand/pose]"
    c = ", container: perception" if container else ""
    cs = c if container == "source" else ""   # the product's layout: the source in the container too
    return f"""
nodes:
  replay: {{node: replay, params: {{source: "{clip}", rate: {rate}}}, required: true{cs}}}
  detector: {{node: detector, params: {{every_frame: true, max_hands: {max_hands}}}, required: true{c}}}
  shape: {{node: shape{c}}}
  ik: {{node: ik, required: true{c}}}
  recorder: {{node: recorder, params: {{output: "{bag}", overwrite: true{topics}}}, required: true}}
"""


def graph_env(run_dir: str) -> dict:
    """This process's environment for a launched graph: none of its HANDMOCAP_ settings, its own run folder."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HANDMOCAP_")}
    env["HANDMOCAP_RUN_DIR"] = run_dir
    return env


def run_graph(tmp: Path, clip: Path, rate: float, record_all: bool, name: str, max_hands: int,
              container: str | None = "source", trace: Path | None = None) -> dict:
    """Launch the chain on `clip`; return pose stamps and receipt times (ns), the CPU seconds
    of the launcher and all its nodes, and the wall time of the run."""
    from handmocap.runtime.bag import iter_messages
    from handmocap.runtime import codec
    bag = tmp / f"{name}.mcap"
    (tmp / f"{name}.yaml").write_text(chain_yaml(clip, bag, rate, record_all, max_hands, container))
    run_dir = tempfile.mkdtemp(prefix="hmb")
    env = graph_env(run_dir)
    if trace is not None:
        trace.mkdir(parents=True, exist_ok=True)
        env["HANDMOCAP_TRACE"] = str(trace)
    cpu0, t0 = children_cpu_s(), time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-m", "handmocap.runtime.launch", str(tmp / f"{name}.yaml")], env=env,
                           capture_output=True, text=True, timeout=600)
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)
    wall, cpu = time.monotonic() - t0, children_cpu_s() - cpu0
    if r.returncode != 0:
        raise SystemExit(f"graph {name} failed:\n{r.stdout}{r.stderr}")
    stamps, received, hands = [], [], []
    for _, type_name, payload, log_ns in iter_messages(bag, topics=["/hand/pose"]):
        m = codec.decode(payload, type_name)
        stamps.append(m["header"]["stamp_ns"])
        received.append(log_ns)
        hands.append(len(m["hands"]))
    return {"stamp": np.array(stamps), "recv": np.array(received), "hands": np.array(hands), "cpu_s": cpu,
            "wall_s": wall}


# the hops and stages of a frame, each from one trace event to another ((node, event, topic); None:
# the frame's capture stamp). publish() called -> received: pack, send and the hop together (in a
# container the receiving thread may run before the sending one records `pub1`, so the two are not split)
TRACE_SEGMENTS = (
    ("replay: capture stamp -> publish()", None, ("replay", "pub0", "/camera/image")),
    ("frame: replay publish -> detector", ("replay", "pub0", "/camera/image"), ("detector", "recv", "/camera/image")),
    ("  of which replay pack + send", ("replay", "pub0", "/camera/image"), ("replay", "pub1", "/camera/image")),
    ("detector compute", ("detector", "recv", "/camera/image"), ("detector", "pub0", "/hand/keypoints")),
    ("keypoints: detector publish -> ik", ("detector", "pub0", "/hand/keypoints"), ("ik", "recv", "/hand/keypoints")),
    ("ik compute", ("ik", "recv", "/hand/keypoints"), ("ik", "pub0", "/hand/pose")),
    ("pose: ik publish -> recorder", ("ik", "pub0", "/hand/pose"), ("recorder", "recv", "/hand/pose")),
    ("total capture -> recorder", None, ("recorder", "recv", "/hand/pose")),
)


def trace_segments_ms(trace: Path) -> tuple[np.ndarray, dict, int]:
    """From the nodes' HANDMOCAP_TRACE files: (F, len(TRACE_SEGMENTS)) ms of each segment per
    frame after the first second (NaN where a frame lacks an event), the CPU ms of each traced
    thread over the run, and the frames traced. Events: each node's receive and publish times
    (`pub0`: publish() called, `pub1`: sent), matched by capture stamp."""
    import json
    ev: dict = {}
    cpu: dict = {}
    for f in trace.glob("*.trace.json"):
        node = f.name.split(".")[0]
        last = {}
        for kind, topic, stamp, t in json.loads(f.read_text()):
            if kind == "cpu":   # CPU time at close of the thread that ran the node (an executor's: shared)
                cpu[topic or node] = t / 1e6
            elif kind == "pub0":
                last[topic] = stamp
                ev[(node, "pub0", topic, stamp)] = t
            elif kind == "pub1":
                ev[(node, "pub1", topic, last.get(topic))] = t
            else:
                ev[(node, "recv", topic, stamp)] = t
    stamps = sorted(s for (n, k, tp, s) in ev if n == "replay" and k == "pub0" and tp == "/camera/image")
    rows = []
    for s in stamps[WARMUP_FRAMES:]:
        row = []
        for _, a, b in TRACE_SEGMENTS:
            ta = s if a is None else ev.get((*a, s))
            tb = s if b is None else ev.get((*b, s))
            row.append(np.nan if ta is None or tb is None else (tb - ta) / 1e6)
        rows.append(row)
    return np.array(rows, float).reshape(-1, len(TRACE_SEGMENTS)), cpu, len(stamps)


def trace_breakdown(trace: Path) -> list[tuple[str, float, float]]:
    """Per-segment p50 / p95 ms (TRACE_SEGMENTS, frames after the first second) and each traced
    thread's CPU per frame, from the nodes' HANDMOCAP_TRACE files."""
    ms, cpu, n = trace_segments_ms(trace)
    out = []
    for k, (label, _, _) in enumerate(TRACE_SEGMENTS):
        d = ms[:, k][np.isfinite(ms[:, k])]
        if len(d):
            out.append((label, float(np.percentile(d, 50)), float(np.percentile(d, 95))))
    for thread, total in sorted(cpu.items()):   # (a "p95" column of the per-frame mean: the same)
        out.append((f"{thread} thread CPU per frame (whole run)", total / n, total / n))   # printed once
    return out


def latency_ms(run: dict) -> np.ndarray:
    return (run["recv"] - run["stamp"]) / 1e6


def throughput(run: dict) -> float:
    """/hand/pose per second of receipt time, after the first WARMUP_FRAMES poses."""
    t = run["recv"][WARMUP_FRAMES:]
    return (len(t) - 1) / ((t[-1] - t[0]) / 1e9)


def in_process(frames: list[np.ndarray], max_hands: int, fps: float | None = None) -> dict:
    """HandTracker.process per frame: wall and CPU ms, after a warm-up pass; back to back,
    or with fps, each frame started on a 1/fps clock as a camera would deliver it (a
    process that waits between frames wakes with cold caches: slower per frame)."""
    from handmocap.perception.tracker import HandTracker
    tracker = HandTracker(max_hands=max_hands)
    for f in frames[:60]:
        tracker.process(f)
    tracker.reset()
    wall, cpu, hands = [], [], []
    t0 = time.perf_counter()
    for i, f in enumerate(frames):
        if fps:
            time.sleep(max(0.0, t0 + i / fps - time.perf_counter()))
        w, c = time.perf_counter(), time.process_time()
        hands.append(len(tracker.process(f)))
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return {"wall_ms": 1e3 * np.array(wall), "cpu_ms": 1e3 * np.array(cpu), "hands": np.array(hands)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames per graph run (>= 90)")
    ap.add_argument("--record-all", action="store_true", help="the recorder records every topic, as demo.yaml")
    ap.add_argument("--max-hands", type=int, default=2, help="the detector's max_hands (2: the product's default; "
                    "1: never a second, spurious track on this one-hand clip)")
    ap.add_argument("--no-container", action="store_true", help="every node its own process (no container)")
    ap.add_argument("--source-outside", action="store_true", help="replay a process of its own, only detector, "
                    "shape and ik in the container (the layout before the source joined it)")
    ap.add_argument("--trace", action="store_true", help="also print the 30 fps run's per-hop times "
                    "(HANDMOCAP_TRACE; tracing itself costs a little)")
    args = ap.parse_args()
    container = None if args.no_container else "perception" if args.source_outside else "source"
    load0 = os.getloadavg()
    tmp = Path(tempfile.mkdtemp(prefix="bench_e2e"))
    try:
        frames = make_clip(tmp / "clip.mp4", args.frames)
        decode_ms = decode_cpu_ms(tmp / "clip.mp4")
        ip_decoding_cpu = in_process_with_decoding_cpu_ms(tmp / "clip.mp4", args.max_hands)
        make_clip(tmp / "short.mp4", WARMUP_FRAMES)
        live = run_graph(tmp, tmp / "clip.mp4", 1.0, args.record_all, "live", args.max_hands, container,
                         trace=tmp / "trace" if args.trace else None)
        hops = trace_breakdown(tmp / "trace") if args.trace else []
        fast = run_graph(tmp, tmp / "clip.mp4", 0.0, args.record_all, "fast", args.max_hands, container)
        short = run_graph(tmp, tmp / "short.mp4", 0.0, args.record_all, "short", args.max_hands, container)
        inproc = in_process(frames, args.max_hands)
        paced = in_process(frames, args.max_hands, fps=30.0)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    load1 = os.getloadavg()

    n = args.frames
    graph_cpu_ms = 1e3 * (fast["cpu_s"] - short["cpu_s"]) / (n - WARMUP_FRAMES)
    lat_live = latency_ms(live)
    p50, p95 = np.percentile(lat_live[WARMUP_FRAMES:], [50, 95])
    fps_fast = throughput(fast)
    ip_wall, ip_cpu = float(np.median(inproc["wall_ms"])), float(np.median(inproc["cpu_ms"]))
    ip_paced = float(np.median(paced["wall_ms"][WARMUP_FRAMES:]))
    over_latency = p50 - ip_paced
    over_cpu = graph_cpu_ms - ip_cpu
    over_wall = 1e3 / fps_fast - ip_wall

    print(f"load average {load0[0]:.2f} at start; {n} frames of 640x480, one hand; max_hands {args.max_hands}; "
          f"recorder: {'every topic' if args.record_all else '/hand/pose only'}; "
          f"{LAYOUTS[container]}")
    print(f"{'row':20s} {'poses':>6s} {'hands/frame':>11s} {'frames/s':>9s} {'p50 ms':>8s} {'p95 ms':>8s} "
          f"{'max ms':>8s} {'ms/frame':>9s} {'CPU ms/frame':>13s}")
    for name, run in (("graph @30 fps", live), ("graph unthrottled", fast)):
        lat = latency_ms(run)[WARMUP_FRAMES:]
        per_frame = 1e3 / throughput(run)
        cpu = f"{graph_cpu_ms:13.2f}" if run is fast else f"{'':>13s}"
        print(f"{name:20s} {len(run['stamp']):6d} {run['hands'].mean():11.2f} {throughput(run):9.1f} "
              f"{np.percentile(lat, 50):8.1f} {np.percentile(lat, 95):8.1f} {lat.max():8.1f} {per_frame:9.2f} {cpu}")
    print(f"{'in-process tracker':20s} {len(inproc['wall_ms']):6d} {inproc['hands'].mean():11.2f} "
          f"{1e3 / ip_wall:9.1f} {ip_wall:8.1f} {np.percentile(inproc['wall_ms'], 95):8.1f} "
          f"{inproc['wall_ms'].max():8.1f} {ip_wall:9.2f} {ip_cpu:13.2f}")
    pw = paced["wall_ms"][WARMUP_FRAMES:]
    print(f"{'in-process @30 fps':20s} {len(paced['wall_ms']):6d} {paced['hands'].mean():11.2f} {30.0:9.1f} "
          f"{ip_paced:8.1f} {np.percentile(pw, 95):8.1f} {pw.max():8.1f} {ip_paced:9.2f} "
          f"{float(np.median(paced['cpu_ms'])):13.2f}")
    print("(in-process: p50/p95/max are per-frame wall times; graph unthrottled: p50/p95/max are queueing, "
          "not latency; graph @30 fps throughput is the source's 30 fps)")
    print(f"start-up at 30 fps: first {WARMUP_FRAMES} frames' latency max {lat_live[:WARMUP_FRAMES].max():.0f} ms, "
          f"p50 {np.median(lat_live[:WARMUP_FRAMES]):.0f} ms (left out of the rows above)")
    print(f"graph CPU per frame: ({fast['cpu_s']:.2f} s over {n} frames - {short['cpu_s']:.2f} s over "
          f"{WARMUP_FRAMES}) / {n - WARMUP_FRAMES} = {graph_cpu_ms:.2f} ms, of which decoding the video "
          f"{decode_ms:.2f} ms (replay's; the in-process row gets decoded frames); load average {load1[0]:.2f} at the end")
    print(f"in-process with decoding (replay's reader + HandTracker in one process, mean): {ip_decoding_cpu:.2f} ms "
          f"CPU per frame; graph CPU {graph_cpu_ms - ip_decoding_cpu:+.2f} ms over it")

    for label, p50_, p95_ in hops:
        if "thread CPU" in label:
            print(f"  trace @30 fps: {label:48s} {p50_:6.2f} ms")
        else:
            print(f"  trace @30 fps: {label:48s} p50 {p50_:6.2f} ms  p95 {p95_:6.2f} ms")

    def verdict(ok):
        return "met" if ok else "NOT MET"
    print(f"unthrottled graph throughput: {fps_fast:.1f} frames/s (target >= 100: {verdict(fps_fast >= 100)}); "
          f"in-process {1e3 / ip_wall:.1f} frames/s")
    print(f"latency at 30 fps, capture -> /hand/pose: p50 {p50:.1f} ms, p95 {p95:.1f} ms "
          f"(target p95 <= 20 ms: {verdict(p95 <= 20)})")
    print(f"graph overhead per frame: latency {over_latency:+.1f} ms (p50 {p50:.1f} - in-process at 30 fps "
          f"{ip_paced:.1f}; {p50 - ip_wall:+.1f} against back-to-back frames), CPU {over_cpu:+.1f} ms "
          f"({graph_cpu_ms:.1f} - {ip_cpu:.1f}; {over_cpu - decode_ms:+.1f} without video decoding), unthrottled wall "
          f"{over_wall:+.1f} ms; CPU over in-process with decoding {graph_cpu_ms - ip_decoding_cpu:+.1f} ms "
          f"(target <= 2 ms, latency, CPU without decoding and CPU over in-process with decoding: "
          f"{verdict(max(over_latency, over_cpu - decode_ms, graph_cpu_ms - ip_decoding_cpu) <= 2)})")


if __name__ == "__main__":
    main()
