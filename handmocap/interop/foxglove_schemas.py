"""Minimal JSON Schemas of the Foxglove well-known message types that `handbag export
--foxglove` and the live bridge (handmocap.interop.foxglove_live) write (written here from the field lists of Foxglove's schema docs; only the
fields we fill are described, Foxglove treats missing optional fields as defaults).

A channel whose schema has encoding `jsonschema`, one of these names and message encoding
`json` is decoded and shown by Foxglove's Image, 3D and Raw Messages panels.
Units: times {sec, nsec} (nsec < 1e9); image coordinates px; 3D metres; colours r,g,b,a in [0,1].
"""
from __future__ import annotations

NUMBER = {"type": "number"}
INTEGER = {"type": "integer"}
STRING = {"type": "string"}
BOOLEAN = {"type": "boolean"}


def _object(**props) -> dict:
    return {"type": "object", "properties": props}


def _array(items: dict, n: int | None = None) -> dict:
    a = {"type": "array", "items": items}
    if n is not None:
        a.update(minItems=n, maxItems=n)
    return a


TIME = _object(sec=INTEGER, nsec=INTEGER)
DURATION = _object(sec=INTEGER, nsec=INTEGER)
COLOR = _object(r=NUMBER, g=NUMBER, b=NUMBER, a=NUMBER)
POINT2 = _object(x=NUMBER, y=NUMBER)
VECTOR3 = _object(x=NUMBER, y=NUMBER, z=NUMBER)
POINT3 = VECTOR3
QUATERNION = _object(x=NUMBER, y=NUMBER, z=NUMBER, w=NUMBER)
POSE = _object(position=VECTOR3, orientation=QUATERNION)

# PointsAnnotation.type and LinePrimitive.type enumerations.
POINTS_ANNOTATION_TYPE = {"UNKNOWN": 0, "POINTS": 1, "LINE_LOOP": 2, "LINE_STRIP": 3, "LINE_LIST": 4}
LINE_TYPE = {"LINE_STRIP": 0, "LINE_LOOP": 1, "LINE_LIST": 2}
DELETION_TYPE = {"MATCHING_ID": 0, "ALL": 1}


def _titled(name: str, schema: dict, description: str) -> dict:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": name,
            "description": description, **schema}


COMPRESSED_IMAGE = _titled("foxglove.CompressedImage", _object(
    timestamp=TIME,
    frame_id=STRING,
    data={"type": "string", "contentEncoding": "base64", "description": "compressed image bytes"},
    format={"type": "string", "description": "jpeg, png, webp or avif"},
), "A compressed image")

CAMERA_CALIBRATION = _titled("foxglove.CameraCalibration", _object(
    timestamp=TIME,
    frame_id=STRING,
    width=INTEGER,
    height=INTEGER,
    distortion_model={"type": "string", "description": "plumb_bob or rational_polynomial"},
    D=_array(NUMBER),
    K=_array(NUMBER, 9),
    R=_array(NUMBER, 9),
    P=_array(NUMBER, 12),
), "Camera calibration parameters (row-major 3x3 K and R, 3x4 P)")

_POINTS_ANNOTATION = _object(
    timestamp=TIME,
    type={"type": "integer", "enum": sorted(POINTS_ANNOTATION_TYPE.values())},
    points=_array(POINT2),
    outline_color=COLOR,
    outline_colors=_array(COLOR),
    fill_color=COLOR,
    thickness=NUMBER,
)
_TEXT_ANNOTATION = _object(
    timestamp=TIME, position=POINT2, text=STRING, font_size=NUMBER,
    text_color=COLOR, background_color=COLOR,
)
_CIRCLE_ANNOTATION = _object(
    timestamp=TIME, position=POINT2, diameter=NUMBER, thickness=NUMBER,
    fill_color=COLOR, outline_color=COLOR,
)
IMAGE_ANNOTATIONS = _titled("foxglove.ImageAnnotations", _object(
    circles=_array(_CIRCLE_ANNOTATION),
    points=_array(_POINTS_ANNOTATION),
    texts=_array(_TEXT_ANNOTATION),
), "Annotations drawn over an image, in pixels")

_SPHERE = _object(pose=POSE, size=VECTOR3, color=COLOR)
_LINE = _object(
    type={"type": "integer", "enum": sorted(LINE_TYPE.values())},
    pose=POSE, thickness=NUMBER, scale_invariant=BOOLEAN,
    points=_array(POINT3), color=COLOR, colors=_array(COLOR), indices=_array(INTEGER),
)
_TRIANGLES = _object(   # points (N,3) metres; indices: 3 per triangle into points (all points in order if empty)
    pose=POSE, points=_array(POINT3), color=COLOR, colors=_array(COLOR), indices=_array(INTEGER),
)
_ENTITY = _object(
    timestamp=TIME, frame_id=STRING, id=STRING, lifetime=DURATION, frame_locked=BOOLEAN,
    metadata=_array(_object(key=STRING, value=STRING)),
    spheres=_array(_SPHERE), lines=_array(_LINE), triangles=_array(_TRIANGLES),
)
_DELETION = _object(
    timestamp=TIME,
    type={"type": "integer", "enum": sorted(DELETION_TYPE.values())},
    id=STRING,
)
SCENE_UPDATE = _titled("foxglove.SceneUpdate", _object(
    deletions=_array(_DELETION),
    entities=_array(_ENTITY),
), "Adds, replaces or deletes entities of a 3D scene")

_FRAME_TRANSFORM = _object(
    timestamp=TIME,
    parent_frame_id=STRING,
    child_frame_id=STRING,
    translation=VECTOR3,
    rotation=QUATERNION,
)
FRAME_TRANSFORM = _titled("foxglove.FrameTransform", _FRAME_TRANSFORM,
                          "Pose of a child frame in its parent frame (metres, unit quaternion)")
FRAME_TRANSFORMS = _titled("foxglove.FrameTransforms", _object(transforms=_array(_FRAME_TRANSFORM)),
                           "Several frame transforms at once")

BY_NAME = {s["title"]: s for s in (COMPRESSED_IMAGE, CAMERA_CALIBRATION, IMAGE_ANNOTATIONS, SCENE_UPDATE,
                                    FRAME_TRANSFORM, FRAME_TRANSFORMS)}
