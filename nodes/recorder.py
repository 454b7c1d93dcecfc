"""recorder: writes topics of the graph to an MCAP bag, payloads byte for byte as received.

Params: `output` (bag path; parent folders are made; an existing file is an error unless
`overwrite` is true), `topics` (list; empty = every topic of the graph). Subscriptions are
keep-all. Each message is stored with its receive time as MCAP log time and its header
stamp as publish time. The bag is finished properly (summary, footer) on SIGINT/SIGTERM and
when every recorded input has ended; a one-line summary is logged at the end.
"""
from __future__ import annotations

from pathlib import Path

from handmocap.bag import BagWriter
from handmocap.node import Node, run

PARAMS = {"output": "out.mcap", "topics": [], "overwrite": False}
IDLE_TICK_S = 0.5   # when nothing arrives this long, close the open chunk if it is old


def open_output(output: str, overwrite: bool) -> BagWriter:
    """A BagWriter on `output`; FileExistsError names the file if it exists and may not be replaced."""
    path = Path(output).expanduser()
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists (remove it, choose another "
                              f"output, or set overwrite:=true)")
    path.parent.mkdir(parents=True, exist_ok=True)
    return BagWriter(path)


def summary_line(counts: dict, path: Path) -> str:
    """'recorded 12 message(s) to out.mcap: /a 10, /b 2'."""
    total = sum(counts.values())
    per_topic = ", ".join(f"{t} {n}" for t, n in sorted(counts.items())) or "no topics"
    return f"recorded {total} message(s) to {path}: {per_topic}"


def main(argv: list[str] | None = None, name: str = "recorder") -> None:
    """Run the recorder; `argv` (name:=value params) defaults to sys.argv[1:]."""
    node = Node(name, params=PARAMS, argv=argv)
    p = node.params
    topics = p["topics"]
    if isinstance(topics, str):
        topics = [topics]
    try:
        bag = open_output(str(p["output"]), bool(p["overwrite"]))
    except Exception:
        node.close()
        raise
    try:
        if topics:
            for topic in topics:
                node.subscribe(topic, None, mode="all")
        else:
            node.subscribe(None, None, mode="all")
        node.log.info("recording %s to %s", ", ".join(topics) or "every topic", bag.path)
        refused: set[str] = set()   # topics seen with a second message type (a graph bug)
        for msg in node.events(timeout=IDLE_TICK_S):
            if msg is None:
                bag.tick()
                continue
            try:
                bag.write(msg.topic, msg.type, msg.raw, msg.recv_ns, msg.stamp_ns)
            except ValueError as e:   # one channel holds one type: keep the first, skip the rest
                if msg.topic not in refused:
                    refused.add(msg.topic)
                    node.log.warning("not recording some messages: %s", e)
    finally:
        bag.close()
        node.log.info("%s", summary_line(bag.counts, bag.path))
        node.close()


if __name__ == "__main__":
    run(main)
