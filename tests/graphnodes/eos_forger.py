"""Test node: once the graph is up, sends forged end-of-stream marks on `topic` naming
`victim` (without a token, and with a wrong one), then ends normally."""
from handmocap.runtime import bus
from handmocap.runtime.node import Node, run

PARAMS = {"topic": "/test/blob", "victim": "ticker"}


def main():
    node = Node("eos_forger", params=PARAMS)
    p = node.params
    topic = node.advertise(p["topic"], "Blob")
    node.wait_for_graph()
    node.wait_for_subscribers(5.0)
    for payload in (p["victim"].encode(), f"{p['victim']}\0{'0' * 16}".encode()):
        node.pub.send(topic, bus.EOS.decode(), payload, eos=True)   # every path: lossy, lossless, control
    node.close()


if __name__ == "__main__":
    run(main)
