"""Test node: well-formed messages with wrong values, into a live graph (issue 49's drill), at
`hz` for `count` rounds, each through the node's real socket with a forged header:
  a HandShape whose beta is NaN, HandKeypoints with a NaN score and with a stamp of 2**64 - 1
  (all three must be refused by every subscriber), and a valid HandKeypoints from "another
  stream" (seq restarting at 0, frame_id camera2), which must not count as a loss. With
  `oversize` > 0, after the rounds it sends that many payloads of `oversize_mib` MiB on both
  topics, `hz` apart (each subscriber must refuse them unread and keep its other inputs)."""
import time

import numpy as np

from handmocap.runtime import codec
from handmocap.runtime.node import Node, run

PARAMS = {"count": 30, "hz": 20.0, "oversize": 0, "oversize_mib": 80}


def hand(score=0.9):
    return {"track_id": 77, "handedness": "right", "score": score, "bbox": np.float32([10, 10, 60, 60]),
            "uv": np.full((21, 2), 30, np.float32), "confidence": np.full(21, 0.8, np.float32),
            "xyz_rel": np.linspace(-0.5, 0.5, 63, dtype=np.float32).reshape(21, 3)}


def main():
    node = Node("value_forger", params=PARAMS)
    shape = node.advertise("/hand/shape", "HandShape")
    keypoints = node.advertise("/hand/keypoints", "HandKeypoints")
    node.publish(keypoints, {"width": 640, "height": 480, "hands": []}, frame_id="camera2")   # waits for the graph
    for i in range(int(node.params["count"])):
        now = time.time_ns()
        forged = codec.header(0, "camera", now)
        node.pub.send(shape, "HandShape", codec.encode({"header": forged, "shapes": [{
            "track_id": 0, "handedness": "right", "beta": np.full(10, np.nan, np.float32),
            "rest_xyz": np.zeros((21, 3), np.float32), "bone_ratios": np.ones(20, np.float32), "samples": 5}]}))
        node.pub.send(keypoints, "HandKeypoints", codec.encode({"header": forged, "width": 640, "height": 480,
                                                                "hands": [hand(float("nan"))]}))
        node.pub.send(keypoints, "HandKeypoints", codec.encode({"header": codec.header(0, "camera", 2**64 - 1),
                                                                "width": 640, "height": 480, "hands": [hand()]}))
        node.pub.send(keypoints, "HandKeypoints", codec.encode({"header": codec.header(i + 1, "camera2", now),
                                                                "width": 640, "height": 480, "hands": []}))
        time.sleep(1 / float(node.params["hz"]))
    if int(node.params["oversize"]):
        huge = b"\0" * (int(node.params["oversize_mib"]) << 20)
        for _ in range(int(node.params["oversize"])):
            node.pub.send(keypoints, "HandKeypoints", huge)
            node.pub.send(shape, "HandShape", huge)
            time.sleep(1 / float(node.params["hz"]))
        # its subscribers make their reset connections again once they see it still alive
        # (node.RESET_JUDGE_S, then a scan): its end of stream, sent sooner, would find none of
        # them and the graph would wait for it
        time.sleep(2.0)
    node.log.info("sent every forged message")
    node.close()


if __name__ == "__main__":
    run(main)
