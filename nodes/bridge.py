"""bridge: the graph, live, in Foxglove Studio (Open connection -> ws://localhost:8765).
/camera/image, /camera/info, /hand/keypoints, /hand/pose -> Foxglove's WebSocket protocol.

A thin loop over handmocap.interop.foxglove_live.LiveBridge (its module docstring has the channel
table): the camera image as JPEG, the calibration, the 2D skeleton over the image, the 3D
skeleton and the posed hand mesh, frame transforms world -> camera -> hand/<id>/wrist, and
the raw /hand/pose as JSON (for Plot panels). Every input is latest-only: a slow viewer
never holds the graph back nor builds a backlog.

Params: host (default 127.0.0.1: nothing listens on the network unless told), port (8765),
images (Image topics to serve), image_hz and mesh_hz (rate caps, 0 = off), world_frame,
camera_pose ([x, y, z, qw, qx, qy, qz] of the camera in the world frame), model (hand model
path, default bundled: the one the ik node uses). Needs the optional extra: pip install -e '.[viz]'.
"""
from __future__ import annotations

from handmocap.interop import foxglove_live
from handmocap.perception.hand_model import HandModel
from handmocap.runtime.node import Node, check_file_param, check_number_param, run

PARAMS = {"host": "127.0.0.1", "port": 8765, "images": ["/camera/image"], "model": None,
          **foxglove_live.LIVE_DEFAULTS}


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param)."""
    check_file_param("bridge", "model", params.get("model"))
    check_number_param("bridge", "port", params.get("port", PARAMS["port"]), minimum=0, integer=True)
    for key in ("image_hz", "mesh_hz"):                       # 0: off
        check_number_param("bridge", key, params.get(key, PARAMS[key]), minimum=0)


def main() -> None:
    node = Node("bridge", params=PARAMS)
    p = node.params
    try:
        server = foxglove_live.start_server(str(p["host"]), int(p["port"]))
    except Exception:
        node.close()
        raise
    try:
        images = [p["images"]] if isinstance(p["images"], str) else p["images"]   # images:=/viz/image
        topics = {node.subscribe(t, "Image", mode="latest"): "Image" for t in images}
        topics[node.subscribe("/camera/info", "CameraInfo", mode="latest")] = "CameraInfo"
        topics[node.subscribe("/hand/keypoints", "HandKeypoints", mode="latest")] = "HandKeypoints"
        topics[node.subscribe("/hand/pose", "HandPose", mode="latest")] = "HandPose"
        bridge = foxglove_live.LiveBridge(topics, foxglove_live.foxglove_channel, HandModel.load(p["model"]), p)
        node.log.info("serving the graph to Foxglove at ws://%s:%d", p["host"], server.port)
        for msg in node:
            bridge.handle(msg.topic, msg.type, msg.data)
    finally:
        server.stop()
        node.close()


if __name__ == "__main__":
    run(main)
