"""Test node: receives `topic` in `mode`, sleeps `work_s` per message, and writes what it saw
(sequence numbers, ages at receipt) as JSON to `out` when its input ends, it is stopped, or
it has `max_messages` (0: no limit)."""
import json
import time

from handmocap.runtime.node import Node, run

PARAMS = {"topic": "/test/blob", "mode": "latest", "work_s": 0.0, "out": "sink.json", "max_messages": 0}


def main():
    node = Node("sink", params=PARAMS)
    p = node.params
    node.subscribe(p["topic"], None, mode=p["mode"])
    seqs, ages_ms = [], []
    for msg in node:
        seqs.append(msg.data["header"]["seq"])
        ages_ms.append((msg.recv_ns - msg.stamp_ns) / 1e6)
        if p["work_s"]:
            time.sleep(p["work_s"])
        if p["max_messages"] and len(seqs) >= p["max_messages"]:   # stops by itself, inputs or not
            break
    dropped = sum(node.stats["dropped"].values())
    lost = sum(node.stats["lost"].values())
    with open(p["out"], "w") as f:
        json.dump({"seqs": seqs, "ages_ms": ages_ms, "dropped": dropped, "lost": lost}, f)
    node.close()


if __name__ == "__main__":
    run(main)
