"""bagplay: a bag as a node of a launched graph (what `handbag play` does from a shell).

Publishes the stored payloads of `file` unchanged on their recorded topics (all, or
`topics`), paced by their log times divided by `rate` (0 = as fast as the graph takes them),
looping if asked; then ends its streams so the graph drains. Header stamps are kept as
recorded (a bag replays the past); use the `replay` node to re-stamp camera frames.
"""
from __future__ import annotations

from pathlib import Path

from handmocap.runtime.bag import play_messages, playable_topics
from handmocap.runtime.node import Node, check_bool_param, check_number_param, run

PARAMS = {"file": None, "rate": 1.0, "loop": False, "topics": []}


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param)."""
    if not params.get("file") or not Path(str(params["file"])).is_file():     # as main() opens it
        raise ValueError(f"bagplay param file: no such bag {params.get('file')}")
    check_number_param("bagplay", "rate", params.get("rate", PARAMS["rate"]), minimum=0)
    check_bool_param("bagplay", "loop", params.get("loop", PARAMS["loop"]))


def main() -> None:
    node = Node("bagplay", params=PARAMS)
    p = node.params
    if not p["file"]:
        raise ValueError("bagplay needs a bag: file:=PATH.mcap")
    topics = playable_topics(p["file"], p["topics"] or None)       # ValueError naming what cannot be played
    for topic, type_name in topics.items():
        node.advertise(topic, type_name)
    sent = play_messages(node, p["file"], topics, float(p["rate"]), bool(p["loop"]))
    node.log.info("played %d message(s) from %s", sent, p["file"])
    node.close()


if __name__ == "__main__":
    run(main)
