"""`handbag export --foxglove`: a copy of a bag whose messages Foxglove Studio decodes.

Every message becomes JSON (message encoding `json`, schema encoding `jsonschema`):
  Image         -> foxglove.CompressedImage (JPEG, base64 in JSON)
  CameraInfo    -> foxglove.CameraCalibration (plumb_bob, K, R = I, P = [K | 0])
  HandKeypoints -> foxglove.ImageAnnotations (bones as a LINE_LIST, joints as POINTS, px)
  HandPose      -> foxglove.SceneUpdate (per hand: joint spheres and bone lines, metres)
  HandMesh      -> foxglove.SceneUpdate (per hand: the posed mesh as triangles, metres) with
                   the faces of the topic's first message that carries them; a topic that
                   never carries faces, as any other message
  anything else -> the message itself as JSON, arrays as nested lists, with a JSON Schema
                   derived from its wire schema (named `handmocap.<Type>`).
Topics keep their names; log times are kept, publish time is the header stamp.
"""
from __future__ import annotations

import base64
import copy
import json
import math
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
from mcap.writer import CompressionType, Writer

from handmocap.runtime import codec
from handmocap.interop import foxglove_schemas as fs
from handmocap.runtime.bag import bag_info, iter_messages
from handmocap.perception.overlay import hand_label
from handmocap.perception.pose import hand_certainty
from handmocap.perception.skeleton import BONES

JPEG_QUALITY = 90
JOINT_SPHERE_M = 0.008          # diameter of a joint sphere in the 3D scene
MESH_ALPHA = 0.6                # see the bones through the skin
MESH_DECIMALS = 4               # vertices to 0.1 mm: a third of the JSON of full float precision
HAND_COLORS = {"right": (0.15, 0.65, 1.0), "left": (1.0, 0.45, 0.15)}   # r, g, b


def foxglove_time(ns: int) -> dict:
    """ns since the epoch -> Foxglove {sec, nsec}."""
    return {"sec": int(ns) // 1_000_000_000, "nsec": int(ns) % 1_000_000_000}


def hand_color(handedness: str, alpha: float = 1.0) -> dict:
    """Foxglove {r, g, b, a} of a hand (HAND_COLORS by handedness)."""
    r, g, b = HAND_COLORS.get(handedness, (0.8, 0.8, 0.8))
    return {"r": r, "g": g, "b": b, "a": alpha}


_color = hand_color
# the pose of a primitive whose points are already in its entity's frame
IDENTITY_POSE = {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                 "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def image_to_compressed(msg: dict) -> dict:
    """Image (bgr8, rgb8, mono8 or jpeg) -> foxglove.CompressedImage with a JPEG."""
    img, encoding = msg["data"], msg["encoding"]
    if encoding == "jpeg":
        jpeg = img.tobytes()
    else:
        if encoding == "rgb8":
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise ValueError(f"JPEG encoding failed for a {encoding} {img.shape} image")
        jpeg = buf.tobytes()
    h = msg["header"]
    return {"timestamp": foxglove_time(h["stamp_ns"]), "frame_id": h["frame_id"],
            "data": base64.b64encode(jpeg).decode("ascii"), "format": "jpeg"}


def camera_info_to_calibration(msg: dict) -> dict:
    """CameraInfo -> foxglove.CameraCalibration (K row-major 9, R identity, P = [K | 0] 12)."""
    K = np.asarray(msg["K"], dtype=np.float64).reshape(3, 3)
    P = np.hstack([K, np.zeros((3, 1))])
    h = msg["header"]
    return {"timestamp": foxglove_time(h["stamp_ns"]), "frame_id": h["frame_id"],
            "width": int(msg["width"]), "height": int(msg["height"]),
            "distortion_model": "plumb_bob", "D": [float(d) for d in msg["distortion"]],
            "K": K.ravel().tolist(), "R": np.eye(3).ravel().tolist(), "P": P.ravel().tolist()}


def _finite_point(p) -> bool:
    return all(math.isfinite(float(v)) for v in p)


def keypoints_to_annotations(msg: dict) -> dict:
    """HandKeypoints -> foxglove.ImageAnnotations: per hand the 20 bones as one LINE_LIST and
    the 21 joints as POINTS (pixels, coloured by handedness), and a label at the box corner."""
    t = foxglove_time(msg["header"]["stamp_ns"])
    points, texts = [], []
    for hand in msg["hands"]:
        uv = np.asarray(hand["uv"], dtype=np.float64)
        color = _color(hand["handedness"])
        bone_pts = [{"x": float(uv[j, 0]), "y": float(uv[j, 1])}
                    for a, b in BONES if _finite_point(uv[a]) and _finite_point(uv[b]) for j in (a, b)]
        joint_pts = [{"x": x, "y": y} for x, y in uv.tolist() if _finite_point((x, y))]
        points.append({"timestamp": t, "type": fs.POINTS_ANNOTATION_TYPE["LINE_LIST"],
                       "points": bone_pts,
                       "outline_color": color, "thickness": 2.0})
        points.append({"timestamp": t, "type": fs.POINTS_ANNOTATION_TYPE["POINTS"],
                       "points": joint_pts, "outline_color": color, "fill_color": color,
                       "thickness": 5.0})
        x0, y0 = (float(v) for v in np.asarray(hand["bbox"])[:2])
        texts.append({"timestamp": t, "position": {"x": x0, "y": max(0.0, y0 - 4.0)},
                      "text": hand_label(hand),
                      "font_size": 14.0, "text_color": color,
                      "background_color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.5}})
    return {"circles": [], "points": points, "texts": texts}


def pose_to_scene_update(msg: dict) -> dict:
    """HandPose -> foxglove.SceneUpdate: deletes the previous hands, then one entity per hand
    (id `hand/<track id>`) with a sphere per joint and the 20 bones as a LINE_LIST, metres,
    in the message's frame (the camera frame, "camera")."""
    h = msg["header"]
    t = foxglove_time(h["stamp_ns"])
    frame = h["frame_id"] or "camera"
    identity = IDENTITY_POSE
    entities = []
    for hand in msg["hands"]:
        xyz = np.asarray(hand["xyz"], dtype=np.float64)
        color = _color(hand["handedness"])
        spheres = [{"pose": {"position": {"x": x, "y": y, "z": z}, "orientation": identity["orientation"]},
                    "size": {"x": JOINT_SPHERE_M, "y": JOINT_SPHERE_M, "z": JOINT_SPHERE_M},
                    "color": color}
                   for x, y, z in xyz.tolist() if _finite_point((x, y, z))]
        bone_pts = [{"x": float(xyz[j, 0]), "y": float(xyz[j, 1]), "z": float(xyz[j, 2])}
                    for a, b in BONES if _finite_point(xyz[a]) and _finite_point(xyz[b]) for j in (a, b)]
        entities.append({
            "timestamp": t, "frame_id": frame, "id": f"hand/{hand['track_id']}",
            "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False,
            "metadata": [{"key": "handedness", "value": hand["handedness"]},
                         {"key": "score", "value": f"{hand['score']:.3f}"},
                         {"key": "confidence", "value": f"{hand_certainty(hand):.3f}"}],
            "spheres": spheres,
            "lines": [{"type": fs.LINE_TYPE["LINE_LIST"], "pose": identity, "thickness": 3.0,
                       "scale_invariant": True, "points": bone_pts, "color": color}],
        })
    return {"deletions": [{"timestamp": t, "type": fs.DELETION_TYPE["ALL"], "id": ""}],
            "entities": entities}


def mesh_entity(t: dict, frame: str, track_id: int, handedness: str, vertices, faces) -> dict:
    """A foxglove.SceneUpdate entity `hand/<track id>/mesh`: one indexed TriangleListPrimitive
    of vertices (V,3) metres in `frame` and faces (F,3) (outward winding), half transparent in
    the hand's colour; t: Foxglove time."""
    points = [{"x": x, "y": y, "z": z} for x, y, z in np.round(np.asarray(vertices), MESH_DECIMALS).tolist()]
    return {"timestamp": t, "frame_id": frame, "id": f"hand/{track_id}/mesh",
            "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False,
            "metadata": [{"key": "handedness", "value": handedness}],
            "triangles": [{"pose": IDENTITY_POSE, "points": points, "color": hand_color(handedness, MESH_ALPHA),
                           "indices": np.asarray(faces).ravel().tolist()}]}


def mesh_to_scene_update(msg: dict, faces) -> dict:
    """HandMesh -> foxglove.SceneUpdate: deletes the previous meshes, then a `mesh_entity` per
    hand. faces (F,3): the right hand's triangles (the message's, or its topic's first
    message's); a left hand's are reversed, its vertices being mirrored. Hands with
    non-finite vertices are left out."""
    h = msg["header"]
    t = foxglove_time(h["stamp_ns"])
    faces = np.asarray(faces)
    entities = [mesh_entity(t, h["frame_id"] or "camera", hand["track_id"], hand["handedness"], hand["vertices"],
                            faces[:, ::-1] if hand["handedness"] == "left" else faces)
                for hand in msg["hands"] if np.all(np.isfinite(hand["vertices"]))]
    return {"deletions": [{"timestamp": t, "type": fs.DELETION_TYPE["ALL"], "id": ""}], "entities": entities}


def _is_array_schema(node: dict) -> bool:
    props = node.get("properties")
    return isinstance(props, dict) and set(props) == {"dtype", "shape", "data"}


def json_schema_for(type_name: str) -> dict:
    """The wire schema of `type_name` with every {dtype, shape, data} array replaced by a JSON
    array (nested lists of numbers, as `to_jsonable` writes them)."""
    def convert(node):
        if isinstance(node, dict):
            if _is_array_schema(node):
                out = {"type": "array", "description": "numeric array as nested lists (C order)"}
                if "description" in node:
                    out["description"] += "; " + node["description"]
                return out
            return {k: convert(v) for k, v in node.items()}
        if isinstance(node, list):
            return [convert(v) for v in node]
        return node
    schema = convert(copy.deepcopy(codec.schema(type_name)))
    schema["title"] = f"handmocap.{type_name}"
    return schema


def to_jsonable(obj):
    """A decoded message -> plain JSON values: arrays as nested lists (NaN/inf as null), bytes as base64."""
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f" and not np.isfinite(obj).all():
            return np.where(np.isfinite(obj), obj, None).tolist()
        return obj.tolist()
    if isinstance(obj, dict):
        return {k: to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return base64.b64encode(bytes(obj)).decode("ascii")
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


CONVERTERS = {
    "Image": (fs.COMPRESSED_IMAGE, image_to_compressed),
    "CameraInfo": (fs.CAMERA_CALIBRATION, camera_info_to_calibration),
    "HandKeypoints": (fs.IMAGE_ANNOTATIONS, keypoints_to_annotations),
    "HandPose": (fs.SCENE_UPDATE, pose_to_scene_update),
}


def first_mesh_faces(src: str | Path, topics=None) -> dict:
    """{topic: faces (F,3)} of each HandMesh topic of bag `src` that carries faces at all (a
    first pass: a Foxglove channel has one schema, so a topic's messages before its faces must
    already be triangles too; the ik node sends them on a connection's first message)."""
    mesh_topics = [t for t, v in bag_info(src)["topics"].items()
                   if v["type"] == "HandMesh" and (topics is None or t in topics)]
    faces = {}
    if not mesh_topics:                     # no pass over a bag of images for nothing
        return faces
    for topic, type_name, payload, _ in iter_messages(src, mesh_topics):
        if topic in faces:
            continue
        try:
            msg = codec.decode(payload, type_name)
        except codec.MalformedMessage:
            continue
        if msg.get("faces") is not None and len(msg["faces"]):
            faces[topic] = np.asarray(msg["faces"]).reshape(-1, 3)
            if len(faces) == len(mesh_topics):
                break                       # every mesh topic's faces known: the rest need not be read
    return faces


def export_foxglove(src: str | Path, dst: str | Path, topics=None) -> dict:
    """Write the Foxglove copy of bag `src` to `dst`; returns {"topics": {topic: {"schema",
    "count"}}, "skipped": {topic: n}} (skipped: payloads that failed to decode)."""
    channels: dict[str, int] = {}
    schemas: dict[str, int] = {}
    written: Counter[str] = Counter()
    skipped: Counter[str] = Counter()
    schema_names: dict[str, str] = {}
    mesh_faces = first_mesh_faces(src, topics)
    with open(dst, "wb") as f:
        out = Writer(f, chunk_size=1024 * 1024, compression=CompressionType.NONE)
        out.start(profile="", library="handmocap foxglove export")
        try:
            for topic, type_name, payload, log_ns in iter_messages(src, topics):
                try:
                    msg = codec.decode(payload, type_name)
                except codec.MalformedMessage:
                    skipped[topic] += 1
                    continue
                schema, convert = CONVERTERS.get(type_name, (None, None))
                if type_name == "HandMesh" and topic in mesh_faces:
                    schema, convert = fs.SCENE_UPDATE, lambda m: mesh_to_scene_update(m, mesh_faces[topic])
                if schema is None:
                    schema, body = json_schema_for(type_name), to_jsonable(msg)
                else:
                    body = convert(msg)
                if topic not in channels:
                    name = schema["title"]
                    if name not in schemas:
                        schemas[name] = out.register_schema(name, "jsonschema", json.dumps(schema).encode())
                    channels[topic] = out.register_channel(topic, "json", schemas[name])
                    schema_names[topic] = name
                data = json.dumps(body, separators=(",", ":"), allow_nan=False).encode()
                out.add_message(channels[topic], log_time=log_ns, data=data,
                                publish_time=msg["header"]["stamp_ns"], sequence=written[topic])
                written[topic] += 1
        finally:
            out.finish()
    return {"topics": {t: {"schema": schema_names[t], "count": n} for t, n in sorted(written.items())},
            "skipped": dict(skipped)}
