"""`handtopic list | nodes | echo TOPIC | hz TOPIC | delay TOPIC`, modelled on `ros2 topic`.

It joins a running graph as an observer (it never holds a graph's start and never ends with
its inputs); `--graph NAME` (or HANDMOCAP_GRAPH) picks the graph, default "default".
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections import deque

import numpy as np

from handmocap.runtime import bus


def _observer(topic: str, mode: str):
    from handmocap.runtime.node import Node
    node = Node(f"_handtopic_{os.getpid()}", observer=True, argv=[])
    node.subscribe(topic, None, mode=mode)
    return node


def topics_table(nodes: dict[str, bus.NodeInfo]) -> dict[str, dict]:
    """{topic: {type, publishers, subscribers}} from the live node files."""
    table: dict[str, dict] = {}
    for n in nodes.values():
        for t, type_name in n.publishes.items():
            table.setdefault(t, {"type": type_name, "publishers": [], "subscribers": []})["publishers"].append(n.name)
    for n in nodes.values():
        for t in n.subscribes:
            if n.observer:
                continue
            for topic in (table if t == "*" else [t]):
                table.setdefault(topic, {"type": "?", "publishers": [], "subscribers": []})["subscribers"].append(n.name)
    return dict(sorted(table.items()))


class NoGraph(Exception):
    """No node of a graph runs in the run dir."""


def live_nodes() -> dict[str, bus.NodeInfo]:
    """The graph's live nodes (tools that only observe left out); NoGraph when there are none."""
    d = bus.run_dir()
    nodes = {n: i for n, i in bus.read_node_files(d).items() if not i.observer}
    if not nodes:
        raise NoGraph(f"no graph is running in {d}: start one with handlaunch, or pick it with --graph NAME "
                      f"(or HANDMOCAP_GRAPH / HANDMOCAP_RUN_DIR)")
    return nodes


def check_topic(topic: str, wait: bool = False) -> bool:
    """Whether a node publishes `topic` now; if not, say so on stderr once, with the closest
    published names (a misspelt name would else wait in silence), and that it waits (`wait`)
    or stops."""
    import difflib
    then = "Waiting for it (Ctrl-C to stop)." if wait else "Pass --wait to wait for a publisher."
    try:
        table = topics_table(live_nodes())
    except NoGraph as e:
        print(f"handtopic: {e}. {then}", file=sys.stderr, flush=True)
        return False
    published = [t for t, row in table.items() if row["publishers"]]
    if topic not in published:
        close = difflib.get_close_matches(topic, published, n=3, cutoff=0.5)
        print(f"handtopic: no node publishes {topic} now" + (f" (did you mean {', '.join(close)}?)" if close else "")
              + f"; published: {', '.join(published) or 'nothing'}. {then}", file=sys.stderr, flush=True)
        return False
    return True


def cmd_list(args) -> int:
    table = topics_table(live_nodes())
    for topic, row in table.items():
        if args.verbose:
            print(f"{topic} [{row['type']}]  pub: {', '.join(row['publishers']) or '-'}  "
                  f"sub: {', '.join(row['subscribers']) or '-'}")
        else:
            print(topic)
    return 0


def cmd_nodes(args) -> int:
    live_nodes()   # NoGraph when nothing runs
    for n in sorted(bus.read_node_files(bus.run_dir(), alive_only=False).values(), key=lambda n: n.name):
        if n.observer and not n.alive:      # a handtopic that was stopped: not part of the graph
            continue
        age = (time.time_ns() - n.heartbeat_ns) / 1e9
        state = "alive" if n.alive else ("ended" if n.ended else "dead")
        pub = sum(n.stats.get("published", {}).values())
        rec = sum(n.stats.get("received", {}).values())
        drop = sum(n.stats.get("dropped", {}).values())
        lost = sum(n.stats.get("lost", {}).values())
        print(f"{n.name:20s} pid {n.pid:<7d} {state:5s} heartbeat {age:5.1f}s ago  "
              f"published {pub}  received {rec}  dropped {drop}  lost {lost}")
    return 0


def _summarise(obj, full: bool):
    if isinstance(obj, np.ndarray):
        if full or obj.size <= 64:
            return obj.tolist()
        return f"<{obj.dtype} array {list(obj.shape)}>"
    if isinstance(obj, dict):
        return {k: _summarise(v, full) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_summarise(v, full) for v in obj]
    return obj


def cmd_echo(args) -> int:
    import yaml
    if not check_topic(args.topic, args.wait) and not args.wait:
        return 1
    node = _observer(args.topic, "all")
    n = 0
    for msg in node.events(timeout=args.duration):
        if msg is None:
            break
        print(yaml.safe_dump(_summarise(msg.data, args.full), sort_keys=False, width=120,
                             default_flow_style=None).rstrip())
        print("---", flush=True)
        n += 1
        if args.count and n >= args.count:
            break
    node.close()
    return 0


def _periodic(args, mode, on_message, report) -> int:
    if not check_topic(args.topic, args.wait) and not args.wait:
        return 1
    node = _observer(args.topic, mode)
    end = time.monotonic() + args.duration if args.duration else None
    next_report = time.monotonic() + 1.0
    for msg in node.events(timeout=0.25):
        if msg is not None:
            on_message(msg)
        now = time.monotonic()
        if now >= next_report:
            report()
            next_report = now + 1.0
        if end and now >= end:
            break
    node.close()
    return 0


def cmd_hz(args) -> int:
    arrivals = deque(maxlen=args.window)
    reported = [0]                  # arrivals[-1] at the last report: a stream that stopped says so

    def report():
        if len(arrivals) < 2 or arrivals[-1] == reported[0]:
            print("no new messages", flush=True)
            return
        reported[0] = arrivals[-1]
        dt = np.diff(np.array(arrivals)) / 1e9
        print(f"average rate: {1 / dt.mean():.3f}\n\tmin: {dt.min():.4f}s max: {dt.max():.4f}s "
              f"std dev: {dt.std():.5f}s window: {len(arrivals)}", flush=True)

    return _periodic(args, "all", lambda m: arrivals.append(m.recv_ns), report)


def cmd_delay(args) -> int:
    """End-to-end latency: receive time minus the header's capture stamp (same host clock)."""
    delays = deque(maxlen=args.window)
    count = [0, 0]                  # messages received, and at the last report

    def report():
        if not delays or count[0] == count[1]:
            print("no new messages", flush=True)
            return
        count[1] = count[0]
        d = np.array(delays) * 1e3
        print(f"delay p50: {np.percentile(d, 50):.2f} ms  p95: {np.percentile(d, 95):.2f} ms  "
              f"min: {d.min():.2f} ms  max: {d.max():.2f} ms  window: {len(d)}", flush=True)

    def on_message(m):
        delays.append((m.recv_ns - m.stamp_ns) / 1e9)
        count[0] += 1

    return _periodic(args, "all", on_message, report)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="handtopic", description=__doc__.splitlines()[0])
    ap.add_argument("--graph", help="graph name (default: $HANDMOCAP_GRAPH or 'default')")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("list", help="topics of the running graph")
    p.add_argument("-v", "--verbose", action="store_true", help="with types, publishers and subscribers")
    sub.add_parser("nodes", help="nodes of the graph, their heartbeat and counters")
    for name, helptext in (("echo", "print messages"), ("hz", "publishing rate"),
                           ("delay", "end-to-end latency (now - header.stamp_ns), p50/p95")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("topic")
        p.add_argument("--duration", type=float, default=None,
                       help="stop after this many seconds (echo: of silence)")
        p.add_argument("--wait", action="store_true",
                       help="wait for a publisher of the topic (default: stop at once when none publishes it)")
        if name == "echo":
            p.add_argument("-n", "--count", type=int, default=0, help="stop after N messages")
            p.add_argument("--full", action="store_true", help="print whole arrays")
        else:
            p.add_argument("--window", type=int, default=1000, help="messages in the statistics window")
    args = ap.parse_args(argv)
    if args.graph:
        os.environ["HANDMOCAP_GRAPH"] = args.graph
    handlers = {"list": cmd_list, "nodes": cmd_nodes, "echo": cmd_echo, "hz": cmd_hz, "delay": cmd_delay}
    try:
        return handlers[args.cmd](args)
    except KeyboardInterrupt:
        return 0
    except (NoGraph, bus.RunDirError) as e:
        print(f"handtopic: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
