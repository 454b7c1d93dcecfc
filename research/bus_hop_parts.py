"""Where a 1 kB bus hop's time goes (issue 51's "1 kB hop <= 1.5x bare pyzmq"), in
benchmarks/bench_bus.py's interleaved rounds (bare and bus messages alternating, 200 Hz):
publish's own call, the header stamp -> `recv_multipart` returned in the subscriber, and that
receive -> the message in the `for msg in node` body (decode, checks, bookkeeping).

    python research/bus_hop_parts.py [--rounds 3]

Session 69 (AMD EPYC, 2 cores): bare 192-223 us end to end; bus stamp -> receive 252-291 us,
receive -> loop 111-120 us, the publish call 179-219 us (hot, the codec's encode is 7 us and its
decode 8.5: the rest is the per-message Python path run with cold caches). The timers themselves
add a little to the bus side.
"""
import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_bus  # noqa: E402


def timed_subscriber(run_dir, topic, type_name, n, q):
    """bench_bus.bus_subscriber, with the time each receive returned: (stamp, received, in the loop) ns."""
    os.environ["HANDMOCAP_RUN_DIR"] = run_dir
    from handmocap.runtime.node import Node
    node = Node("bench_sub", argv=[])
    node.subscribe(topic, type_name, mode="all")
    received, recv = [], node._recv

    def timed_recv(*args, **kwargs):
        frames = recv(*args, **kwargs)
        received.append(time.time_ns())
        return frames
    node._recv = timed_recv
    rows = []
    for msg in node:
        rows.append((msg.stamp_ns, received[-1], time.time_ns()))
        if len(rows) == n:
            break
    q.put(rows)
    node.close()


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--messages", type=int, default=1000)
    args = p.parse_args()
    from handmocap.runtime.node import Node
    publish, publish_us = Node.publish, []

    def timed_publish(self, *a, **k):
        t = time.perf_counter_ns()
        publish(self, *a, **k)
        publish_us.append((time.perf_counter_ns() - t) / 1e3)
    Node.publish = timed_publish
    bench_bus.bus_subscriber = timed_subscriber
    for r in range(args.rounds):
        bare, bus = bench_bus.one_round("small", args.messages, 200)   # bus: (n, 3) us
        stamp, received, looped = bus[:, 0], bus[:, 1], bus[:, 2]
        print(f"round {r}: bare p50 {np.median(bare):.0f} us; bus: stamp -> receive {np.median(received - stamp):.0f} us, "
              f"receive -> loop {np.median(looped - received):.0f} us, stamp -> loop {np.median(looped - stamp):.0f} us; "
              f"publish call {np.median(publish_us[-args.messages:]):.0f} us")


if __name__ == "__main__":
    main()
