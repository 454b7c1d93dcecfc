"""Test node: republishes every Blob of `input` on `output` (keep-all)."""
from handmocap.runtime.node import Node, run

PARAMS = {"input": "/a", "output": "/b"}


def main():
    node = Node("relay", params=PARAMS)
    node.subscribe(node.params["input"], "Blob", mode="all")
    out = node.advertise(node.params["output"], "Blob")
    for msg in node:
        node.publish(out, {"data": msg.data["data"]})
    node.close()


if __name__ == "__main__":
    run(main)
