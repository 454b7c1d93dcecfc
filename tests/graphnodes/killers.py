"""Test node: the four messages that once stopped a whole graph (issue 30), interleaved with
`frames` good 64x48 images on /camera/image, and hands with NaN keypoints on /hand/keypoints,
all through the node's real socket:
  an Image whose data is 1-D; an Image of shape (0,0,3); an Image whose data has shape
  [2**64-1, 0] (once an undeclared extra key's, which is now dropped unread); a list nested 1,000
  deep."""
import msgpack
import numpy as np

from handmocap.runtime import codec
from handmocap.runtime.node import Node, run

PARAMS = {"frames": 20}
W, H = 64, 48


def image_killers(stamp_ns: int):
    """The four payloads, as a publisher would send them (msgpack, typed Image)."""
    h = codec.header(0, stamp_ns=stamp_ns)
    wire = lambda a: {"dtype": "uint8", "shape": list(a.shape), "data": a.tobytes()}
    base = {"header": h, "encoding": "bgr8", "width": W, "height": H}
    deep = []
    leaf = deep
    for _ in range(1000):
        leaf.append([])
        leaf = leaf[0]
    yield "1-D data", msgpack.packb({**base, "data": wire(np.zeros(W * H * 3, np.uint8))})
    yield "(0,0,3) data", msgpack.packb({**base, "data": wire(np.zeros((0, 0, 3), np.uint8))})
    good = wire(np.zeros((H, W, 3), np.uint8))
    yield "huge array", msgpack.packb({**base, "data": {"dtype": "uint8", "shape": [2**64 - 1, 0], "data": b""}})
    yield "nested 1,000 deep", msgpack.packb({**base, "data": good, "extra": deep})


def nan_keypoints(stamp_ns: int) -> bytes:
    hand = {"track_id": 0, "handedness": "right", "score": 0.9, "bbox": np.float32([0, 0, 10, 10]),
            "uv": np.full((21, 2), np.nan, np.float32), "confidence": np.ones(21, np.float32),
            "xyz_rel": np.zeros((21, 3), np.float32)}
    return codec.encode({"header": codec.header(0, stamp_ns=stamp_ns), "width": W, "height": H, "hands": [hand]})


def main():
    node = Node("killers", params=PARAMS)
    image = node.advertise("/camera/image", "Image")
    keypoints = node.advertise("/hand/keypoints", "HandKeypoints")
    frame = np.full((H, W, 3), 90, np.uint8)
    for i in range(int(node.params["frames"])):
        node.publish(image, {"encoding": "bgr8", "width": W, "height": H, "data": frame})   # first: waits for the graph
        stamp = codec.header(0)["stamp_ns"]
        for _, payload in image_killers(stamp):
            node.pub.send(image, "Image", payload)   # both sockets: keep-all and lossless subscribers get them
        node.pub.send(keypoints, "HandKeypoints", nan_keypoints(stamp))
    node.close()


if __name__ == "__main__":
    run(main)
