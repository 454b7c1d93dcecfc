"""The graph, live, in Foxglove: what the `bridge` node (nodes/bridge.py) serves over Foxglove's
WebSocket protocol, as plain conversions plus one small class that knows no bus.

Every channel is JSON (schema encoding `jsonschema`, handmocap.interop.foxglove_schemas), the same
conversions as `handbag export --foxglove` (handmocap.interop.foxglove_export) where they exist:

| graph topic (type)           | Foxglove topic          | schema                        | rate            |
|------------------------------|-------------------------|-------------------------------|-----------------|
| /camera/image (Image)        | same                    | foxglove.CompressedImage JPEG | <= image_hz     |
| /camera/info (CameraInfo)    | same                    | foxglove.CameraCalibration    | <= 2 Hz         |
| /hand/keypoints (HandKeypoints) | same                 | foxglove.ImageAnnotations     | every message   |
| /hand/pose (HandPose)        | same                    | handmocap.HandPose (raw, JSON) | every message  |
|                              | /hand/pose/skeleton     | foxglove.SceneUpdate          | every message   |
|                              | /hand/pose/mesh         | foxglove.SceneUpdate (triangles) | <= mesh_hz   |
| (any of the above)           | /tf                     | foxglove.FrameTransforms      | with each pose, image |

Frames: `<world>` (z up) -> the camera frame (the messages' header frame_id, OpenCV axes) ->
`hand/<track id>/wrist` (the hand's wrist joint and its global rotation quat[0]). 3D is in
metres. Nothing is converted for a channel that no Foxglove client subscribes to, so an
idle bridge costs only the decode of what it receives.
"""
from __future__ import annotations

import json
import math
import time

import numpy as np

from handmocap.interop import foxglove_schemas as fs
from handmocap.interop.foxglove_export import (
    camera_info_to_calibration, foxglove_time, image_to_compressed, json_schema_for, keypoints_to_annotations,
    mesh_entity, pose_to_scene_update, to_jsonable,
)
from handmocap.perception.pose import hand_mesh
from handmocap.perception.rotations import mirror_quat

# World from camera for a camera looking at the scene horizontally: camera x -> world x,
# camera y (down) -> world -z, camera z (forward) -> world y. [x, y, z (m), qw, qx, qy, qz].
CAMERA_IN_WORLD = [0.0, 0.0, 0.0, math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0]
CALIBRATION_HZ = 2.0      # sources repeat CameraInfo with every frame; Foxglove needs it rarely

LIVE_DEFAULTS = {"image_hz": 15.0, "mesh_hz": 15.0, "world_frame": "world", "camera_pose": CAMERA_IN_WORLD}


# -- plain conversions ---------------------------------------------------------------------------
def _quat_xyzw(q_wxyz) -> dict:
    w, x, y, z = (float(v) for v in q_wxyz)
    return {"x": x, "y": y, "z": z, "w": w}


def frame_transform(stamp_ns: int, parent: str, child: str, translation, rotation_wxyz) -> dict:
    """One foxglove.FrameTransform: the child frame's origin (3,) metres and rotation (w, x, y,
    z) in the parent frame."""
    x, y, z = (float(v) for v in translation)
    return {"timestamp": foxglove_time(stamp_ns), "parent_frame_id": parent, "child_frame_id": child,
            "translation": {"x": x, "y": y, "z": z}, "rotation": _quat_xyzw(rotation_wxyz)}


def camera_transform(stamp_ns: int, camera_frame: str, world_frame: str, camera_pose=CAMERA_IN_WORLD) -> dict:
    """FrameTransform world -> camera; camera_pose [x, y, z (m), qw, qx, qy, qz] of the camera in
    the world (default CAMERA_IN_WORLD: camera at the origin, world z up)."""
    if len(camera_pose) != 7:
        raise ValueError(f"camera_pose must be [x, y, z, qw, qx, qy, qz], got {camera_pose!r}")
    return frame_transform(stamp_ns, world_frame, camera_frame, camera_pose[:3], camera_pose[3:])


def wrist_rotation(hand: dict) -> np.ndarray:
    """(4,) (w, x, y, z) rotation of a HandPose hand's wrist frame in the camera frame: quat[0]
    for a right hand; for a left hand (whose quat is that of the mirrored, right-hand model)
    the mirrored rotation M R M, M = diag(-1, 1, 1): the frame of a mirrored (left) model."""
    q = np.asarray(hand["quat"][0], dtype=np.float64)
    return mirror_quat(q) if hand["handedness"] == "left" else q


def hand_transforms(msg: dict) -> list[dict]:
    """HandPose -> FrameTransforms camera -> `hand/<track id>/wrist` (origin at joint 0), one per
    hand whose wrist is finite."""
    h = msg["header"]
    out = []
    for hand in msg["hands"]:
        origin, rot = np.asarray(hand["xyz"][0]), wrist_rotation(hand)
        if np.all(np.isfinite(origin)) and np.all(np.isfinite(rot)):
            out.append(frame_transform(h["stamp_ns"], h["frame_id"] or "camera",
                                       f"hand/{hand['track_id']}/wrist", origin, rot))
    return out


def pose_to_mesh_update(msg: dict, model) -> dict:
    """HandPose -> foxglove.SceneUpdate: deletes the previous meshes, then per hand an entity
    `hand/<track id>/mesh` with one indexed TriangleListPrimitive (points metres, camera frame,
    3 indices per face), half transparent in the hand's colour. Hands with a non-finite
    rotation, shape or root are left out."""
    h = msg["header"]
    t = foxglove_time(h["stamp_ns"])
    entities = []
    for hand in msg["hands"]:
        if not all(np.all(np.isfinite(hand[k])) for k in ("quat", "beta", "root")):
            continue
        vertices, faces, _ = hand_mesh(model, hand)
        entities.append(mesh_entity(t, h["frame_id"] or "camera", hand["track_id"], hand["handedness"], vertices,
                                    faces))
    return {"deletions": [{"timestamp": t, "type": fs.DELETION_TYPE["ALL"], "id": ""}], "entities": entities}


def to_json_bytes(body: dict) -> bytes:
    """Compact JSON; NaN/inf are an error (the conversions drop or null them: JSON has none)."""
    return json.dumps(body, separators=(",", ":"), allow_nan=False).encode()


# -- the live bridge, without the bus or the server ------------------------------------------------
class RateLimit:
    """`hz` events per second per key on average, on the monotonic clock (hz <= 0: never).

    Events are let through on a schedule of slots 1/hz apart, each open from a quarter period
    early: a 30 Hz camera capped at 15 Hz gives every second frame despite its jitter (a plain
    "at least 1/hz since the last one" would give every third frame whenever the second one
    came a little early). After a pause the schedule restarts rather than bursting."""

    def __init__(self):
        self.next = {}

    def allow(self, key: str, hz: float, now: float | None = None) -> bool:
        if hz <= 0:
            return False
        now = time.monotonic() if now is None else now
        period = 1.0 / hz
        slot = self.next.get(key)
        if slot is not None and now < slot - period / 4:
            return False
        self.next[key] = slot + period if slot is not None and now < slot + period else now + period
        return True


def foxglove_channel(topic: str, schema: dict):
    """A JSON channel of the foxglove-sdk (the process's default context: the running server)."""
    import foxglove
    return foxglove.Channel(topic, schema=schema, message_encoding="json")


class LiveBridge:
    """Turns decoded graph messages into Foxglove messages and logs them on channels.

    topics: {graph topic: message type} to serve (Image, CameraInfo, HandKeypoints, HandPose);
    every channel is made here, at once, so a client sees all topics before data flows.
    make_channel(topic, schema) returns an object with `log(bytes, log_time=ns)` and
    `has_sinks()` (foxglove_channel, or a fake in tests); model: the HandModel for meshes;
    params: LIVE_DEFAULTS overrides. Log times are the messages' capture stamps (ns).
    """

    def __init__(self, topics: dict[str, str], make_channel, model, params: dict | None = None):
        self.p = {**LIVE_DEFAULTS, **(params or {})}
        camera_transform(0, "camera", "world", self.p["camera_pose"])   # a bad camera_pose fails now
        self.model = model
        self.rate = RateLimit()
        self.channels = {}
        schemas = {"Image": fs.COMPRESSED_IMAGE, "CameraInfo": fs.CAMERA_CALIBRATION,
                   "HandKeypoints": fs.IMAGE_ANNOTATIONS}
        for topic, type_name in topics.items():
            if type_name == "HandPose":
                self.channels[topic] = make_channel(topic, json_schema_for("HandPose"))
                self.channels[f"{topic}/skeleton"] = make_channel(f"{topic}/skeleton", fs.SCENE_UPDATE)
                self.channels[f"{topic}/mesh"] = make_channel(f"{topic}/mesh", fs.SCENE_UPDATE)
            elif type_name in schemas:
                self.channels[topic] = make_channel(topic, schemas[type_name])
            else:
                raise ValueError(f"the bridge cannot serve {type_name} ({topic})")
        self.channels["/tf"] = make_channel("/tf", fs.FRAME_TRANSFORMS)

    def _wanted(self, topic: str, hz: float | None = None) -> bool:
        """Someone listens on `topic` (and, with hz, its rate allows one more now)."""
        return self.channels[topic].has_sinks() and (hz is None or self.rate.allow(topic, hz))

    def _log(self, topic: str, body: dict, stamp_ns: int) -> None:
        self.channels[topic].log(to_json_bytes(body), log_time=int(stamp_ns))

    def handle(self, topic: str, type_name: str, msg: dict) -> None:
        """One decoded graph message (header included) -> zero or more Foxglove messages."""
        stamp, frame = msg["header"]["stamp_ns"], msg["header"]["frame_id"] or "camera"
        transforms = []
        if type_name == "Image":
            if self._wanted(topic, self.p["image_hz"]):
                self._log(topic, image_to_compressed(msg), stamp)
                transforms.append(camera_transform(stamp, frame, self.p["world_frame"], self.p["camera_pose"]))
        elif type_name == "CameraInfo":
            if self._wanted(topic, CALIBRATION_HZ):
                self._log(topic, camera_info_to_calibration(msg), stamp)
        elif type_name == "HandKeypoints":
            if self._wanted(topic):
                self._log(topic, keypoints_to_annotations(msg), stamp)
        elif type_name == "HandPose":
            if self._wanted(topic):
                self._log(topic, to_jsonable(msg), stamp)
            if self._wanted(f"{topic}/skeleton"):
                self._log(f"{topic}/skeleton", pose_to_scene_update(msg), stamp)
            if self._wanted(f"{topic}/mesh", self.p["mesh_hz"]):
                self._log(f"{topic}/mesh", pose_to_mesh_update(msg, self.model), stamp)
            transforms += [camera_transform(stamp, frame, self.p["world_frame"], self.p["camera_pose"]),
                           *hand_transforms(msg)]
        if transforms and self._wanted("/tf"):
            self._log("/tf", {"transforms": transforms}, stamp)


def start_server(host: str = "127.0.0.1", port: int = 8765, name: str = "handmocap"):
    """Start foxglove-sdk's WebSocket server; the expected failures become one-line
    RuntimeErrors (the SDK not installed, the port taken)."""
    try:
        import foxglove
    except ImportError:
        raise RuntimeError("the Foxglove bridge needs foxglove-sdk, an optional extra: "
                           "pip install -e '.[viz]'") from None
    try:
        return foxglove.start_server(name=name, host=host, port=int(port))
    except RuntimeError as e:
        if "in use" in str(e).lower():
            raise RuntimeError(f"cannot serve Foxglove on {host}:{port}: the port is already in use "
                               f"(another bridge?); choose another with port:=N") from None
        raise RuntimeError(f"cannot serve Foxglove on {host}:{port}: {e}") from None
