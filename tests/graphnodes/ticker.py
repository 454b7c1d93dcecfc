"""Test node: publishes `count` Blob messages of `size` bytes on `topic` at `hz` (0: flat out);
with `fail_after` >= 0 it fails (exit 2) after that many."""
import time

import numpy as np

from handmocap.runtime.node import Node, run

PARAMS = {"topic": "/test/blob", "count": 100, "size": 16, "hz": 0.0, "fail_after": -1}


def main():
    node = Node("ticker", params=PARAMS)
    p = node.params
    node.advertise(p["topic"], "Blob")
    payload = np.zeros(p["size"], np.uint8)
    t0 = time.monotonic()
    for i in range(p["count"]):
        if not node.ok():
            break
        if p["hz"]:
            time.sleep(max(0.0, t0 + i / p["hz"] - time.monotonic()))
        if i == p["fail_after"]:
            raise RuntimeError(f"failing on purpose after {i} messages")
        node.publish(p["topic"], {"data": payload})
    node.close()


if __name__ == "__main__":
    run(main)
