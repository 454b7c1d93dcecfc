"""Test node: interleaves `valid` good Blob messages with malformed frames of every kind on
`topic` (garbage bytes, truncated msgpack, wrong schema, wrong array size, wrong type name,
wrong frame count, and `oversize` bytes where it is not 0), all through the node's real socket,
`pause_s` between rounds."""
import random
import time

import msgpack
import numpy as np

from handmocap.runtime import codec
from handmocap.runtime.node import Node, run

PARAMS = {"topic": "/test/blob", "valid": 50, "seed": 0, "oversize": 0, "pause_s": 0.02}


def malformed(rng: random.Random, oversize: int):
    good = codec.encode({"header": codec.header(0), "data": np.zeros(8, np.uint8)})
    yield "garbage", [b"", b"Blob", rng.randbytes(rng.randint(0, 300))]
    yield "truncated", [b"", b"Blob", good[: rng.randint(1, len(good) - 1)]]
    yield "schema", [b"", b"Blob", msgpack.packb({"header": {"stamp_ns": "x", "seq": 1, "frame_id": "c"}})]
    yield "array-size", [b"", b"Blob", msgpack.packb({"header": codec.header(0),
                                                     "data": {"dtype": "uint8", "shape": [9], "data": b"1"}})]
    yield "unknown-type", [b"", b"NoSuchType", good]
    yield "type-mismatch", [b"", b"Image", good]
    yield "frames", [b"", good]
    if oversize:   # (0: none; over a socket's ZMQ_MAXMSGSIZE it ends the connection, not only the message)
        yield "oversized", [b"", b"Blob", b"\x00" * oversize]


def main():
    node = Node("fuzzer", params=PARAMS)
    p = node.params
    topic = node.advertise(p["topic"], "Blob")
    rng = random.Random(p["seed"])
    node.publish(topic, {"data": np.zeros(8, np.uint8)})   # waits for the graph, like any source
    sent_bad = 0
    for i in range(1, p["valid"]):
        for kind, frames in malformed(rng, p["oversize"]):
            frames[0] = topic.encode() + b"\0"
            node.pub.sock.send_multipart(frames)
            sent_bad += 1
        node.publish(topic, {"data": np.full(8, i % 256, np.uint8)})
        time.sleep(p["pause_s"])   # a keep-all subscriber's queue is bounded (bus: Queues): not a flood
    node.log.info("sent %d valid and %d malformed messages", p["valid"], sent_bad)
    node.close()


if __name__ == "__main__":
    run(main)
