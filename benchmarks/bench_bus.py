"""Per-hop latency of the bus against bare pyzmq PUB/SUB, in the same run.

    python benchmarks/bench_bus.py [--small 2000] [--frames 300]

Two processes, one hop over ipc://. Bus: `Node.publish` (header, msgpack, raw array bytes)
→ `for msg in node` (receive, schema validation, arrays as views); latency = time the
subscriber holds the decoded message − header stamp. Bare: `send_multipart([stamp, bytes])`
→ `recv_multipart`; latency = receive time − stamp. Messages are paced (200 Hz small,
30 Hz frames) so that this measures latency, not queueing.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import tempfile
import time

import numpy as np
import zmq

CASES = {  # row name: which payload (small: small_body(), frame: frame_body())
    "1 kB HandKeypoints": "small",
    "640x480 BGR Image": "frame",
}


def small_body():
    rng = np.random.default_rng(0)
    hand = {"track_id": 0, "handedness": "right", "score": 0.9, "bbox": np.zeros(4, np.float32),
            "uv": rng.random((21, 2), dtype=np.float32), "confidence": np.ones(21, np.float32),
            "xyz_rel": rng.random((21, 3), dtype=np.float32)}
    return "HandKeypoints", {"width": 640, "height": 480, "hands": [hand]}


def frame_body():
    img = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    return "Image", {"encoding": "bgr8", "width": 640, "height": 480, "data": img}


def bus_subscriber(run_dir, topic, type_name, n, q):
    os.environ["HANDMOCAP_RUN_DIR"] = run_dir
    from handmocap.node import Node
    node = Node("bench_sub", argv=[])
    node.subscribe(topic, type_name, mode="all")
    lat = []
    for msg in node:
        lat.append(msg.recv_ns - msg.stamp_ns)
        if len(lat) == n:
            break
    q.put(lat)
    node.close()


def bus_case(kind, n, hz):
    type_name, body = small_body() if kind == "small" else frame_body()
    run_dir = tempfile.mkdtemp(prefix="hmb")
    os.environ["HANDMOCAP_RUN_DIR"] = run_dir
    from handmocap.node import Node
    node = Node("bench_pub", argv=[])
    topic = node.advertise("/bench", type_name)
    q = mp.Queue()
    p = mp.Process(target=bus_subscriber, args=(run_dir, topic, type_name, n, q))
    p.start()
    while node.pub.subscriber_count(topic) < 1:
        time.sleep(0.01)
    time.sleep(0.2)
    for _ in range(n):
        node.publish(topic, body)
        time.sleep(1 / hz)
    lat = q.get(timeout=60)
    p.join()
    node.close()
    return np.array(lat) / 1e3


def bare_subscriber(endpoint, n, q):
    ctx = zmq.Context()
    s = ctx.socket(zmq.SUB)
    s.setsockopt(zmq.RCVHWM, 0)
    s.connect(endpoint)
    s.subscribe(b"")
    lat = []
    while len(lat) < n:
        stamp, payload = s.recv_multipart()
        lat.append(time.time_ns() - int(stamp))
    q.put(lat)


def bare_case(kind, n, hz):
    size = 786 if kind == "small" else 640 * 480 * 3   # the bus's HandKeypoints payload is 786 B
    payload = os.urandom(size)
    endpoint = f"ipc://{tempfile.mkdtemp(prefix='hmb')}/bare.pub"
    ctx = zmq.Context()
    s = ctx.socket(zmq.XPUB)
    s.setsockopt(zmq.SNDHWM, 0)
    s.bind(endpoint)
    q = mp.Queue()
    p = mp.Process(target=bare_subscriber, args=(endpoint, n, q))
    p.start()
    s.recv()   # the subscription arrived
    time.sleep(0.2)
    for _ in range(n):
        s.send_multipart([str(time.time_ns()).encode(), payload], copy=size < 65536)
        time.sleep(1 / hz)
    lat = q.get(timeout=60)
    p.join()
    s.close()
    return np.array(lat) / 1e3


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", type=int, default=2000, help="1 kB messages per case")
    ap.add_argument("--frames", type=int, default=300, help="640x480 frames per case")
    args = ap.parse_args()
    print(f"{'message':22s} {'path':10s} {'p50 us':>9s} {'p95 us':>9s}")
    ratios = {}
    for name, kind in CASES.items():
        n, hz = (args.small, 200) if kind == "small" else (args.frames, 30)
        warm = max(10, n // 20)
        bare = bare_case(kind, n, hz)[warm:]
        busl = bus_case(kind, n, hz)[warm:]
        for label, lat in (("bare pyzmq", bare), ("handmocap", busl)):
            print(f"{name:22s} {label:10s} {np.percentile(lat, 50):9.1f} {np.percentile(lat, 95):9.1f}")
        ratios[name] = (np.percentile(busl, 50) / np.percentile(bare, 50), np.percentile(busl, 95) / np.percentile(bare, 95))
    for name, (r50, r95) in ratios.items():
        print(f"ratio bus/bare {name}: p50 {r50:.2f}x  p95 {r95:.2f}x  (target p50 <= 1.5x)")


if __name__ == "__main__":
    mp.set_start_method("spawn")
    main()
