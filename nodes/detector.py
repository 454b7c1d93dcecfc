"""detector: every hand's 2D and normalized 3D keypoints. /camera/image -> /hand/keypoints.

A thin loop over handmocap.perception.detector.HandDetector (hand finder when a track is lost or every
`redetect_every` frames, `redetect_every_full` while every track slot is held, DetNet on a 128 px
crop per tracked hand, crops tracked from the previous 2D joints, left hands mirrored into the
right-hand network, stable track ids).
Takes the freshest image only (latest-only: a live camera never builds a backlog), or with
every_frame:=true every image in order (offline processing of a recording); publishes one
HandKeypoints per processed image with its stamp; `hands` may be empty.

Params: detnet (ONNX path, or null (the default: models/detnet_lite0_int8.onnx, pretrained
features, with the side from models/detnet_int8.onnx) / "int8" (models/detnet_int8.onnx alone) /
"float32" (models/detnet.onnx) / "lite0" (alone: its own side is worse)), side_detnet (the DetNet
whose handedness head gives the side, the same names; null: int8's for the default detnet, else
detnet's own; "none": detnet's own), finder (ONNX path, default models/finder.onnx; "none": try
the centre square of the frame), grey_finder (the finder run on grey frames, a mono or IR
camera's: ONNX path, default models/finder_grey.onnx with the bundled finder; "none": `finder`
on every frame), grey_detnet (the DetNet run on grey frames: ONNX path, default
models/detnet_grey_int8.onnx with the bundled DetNet; "none": `detnet` on every frame), threads
(onnxruntime intra-op threads per network), every_frame; and every HandDetector setting, the
fields of DetectorSettings (handmocap/perception/detector.py, each explained beside it; the
table in docs/reference.md, "Detector settings", is made from them).
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from handmocap.perception.crops import CROP
from handmocap.perception.detector import DetectorSettings, HandDetector
from handmocap.perception.detnet_runner import DETNET_GREY, DETNET_NAMES, detnet_path
from handmocap.runtime.frames import frame_bgr
from handmocap.perception.hand_finder import DEFAULT_PATH as FINDER_PATH, GREY_PATH as GREY_FINDER_PATH
from handmocap.runtime.node import Message, Node, check_bool_param, check_file_param, check_number_param, run, spin

# HandDetector's settings a launch file may set, with their defaults: every DetectorSettings
# field (each documented there), those typed `| None` taking null
TUNABLE = tuple(f.name for f in dataclasses.fields(DetectorSettings))
NULLABLE = DetectorSettings.nullable()
_DEFAULTS = DetectorSettings()
PARAMS = {"detnet": None, "side_detnet": None, "finder": None, "grey_finder": None, "grey_detnet": None, "threads": 1,
          **{k: getattr(_DEFAULTS, k) for k in TUNABLE}, "every_frame": False}


def setting(name: str, value):
    """A TUNABLE param as HandDetector takes it: null stays None (off) where the class allows
    it (NULLABLE), a number the default's type (int or float), handedness "left" or "right", a
    word where the default is one (turn_by)."""
    if value is None:
        if name not in NULLABLE:
            raise ValueError(f"detector param {name}: expected a number, got null")
        return None
    if name == "handedness":
        if value not in ("left", "right"):
            raise ValueError(f"detector param handedness: expected left, right or null, got {value!r}")
        return value
    if isinstance(PARAMS[name], str):             # a word (turn_by): DetectorSettings checks which
        if not isinstance(value, str):
            raise ValueError(f"detector param {name}: expected a word, got {value!r}")
        return value
    if isinstance(PARAMS[name], bool):
        if not isinstance(value, bool):
            raise ValueError(f"detector param {name}: expected true or false, got {value!r}")
        return value
    try:
        if isinstance(value, (bool, str)):
            raise TypeError
        return type(PARAMS[name])(value)
    except (TypeError, ValueError):
        raise ValueError(f"detector param {name}: expected a number or null, got {value!r}") from None


def check_params(params: dict) -> None:
    """The launcher's check of a graph's detector params before any process starts: the model
    files exist, each HandDetector setting given reads as `setting` reads it, and together
    they pass DetectorSettings' own check (ValueError naming the setting)."""
    check_file_param("detector", "detnet", params.get("detnet"), tuple(DETNET_NAMES), "handtrain detnet")
    check_file_param("detector", "side_detnet", params.get("side_detnet"), (*DETNET_NAMES, "none"), "handtrain detnet")
    check_file_param("detector", "finder", params.get("finder"), ("none",), "handtrain finder")
    check_file_param("detector", "grey_finder", params.get("grey_finder"), ("none",), "handtrain finder --grey 0.2")
    check_file_param("detector", "grey_detnet", params.get("grey_detnet"), ("none",), "handtrain detnet --grey 1")
    given = {name: setting(name, params[name]) for name in TUNABLE if name in params}
    try:
        DetectorSettings(**given)           # the ranges the settings declare (variant counts, ...)
    except ValueError as e:
        raise ValueError(f"detector param {e}") from None
    check_number_param("detector", "threads", params.get("threads", PARAMS["threads"]), minimum=1, integer=True)
    check_bool_param("detector", "every_frame", params.get("every_frame", PARAMS["every_frame"]))


def warm_up(detector: HandDetector, params: dict) -> None:
    """Run each network once on blank input before the graph starts: onnxruntime sets up its
    buffers on a session's first run (tens of ms here), which would otherwise hold up the
    first frames. A file that loads but is not the network it should be fails here, as one
    error line naming it."""
    for detnet, name in ((detector.detnet, detnet_path(params.get("detnet"))),
                         (detector.grey_detnet, params.get("grey_detnet") or DETNET_GREY)):
        if detnet is None:
            continue
        try:
            side = getattr(detnet, "crop_side", CROP)
            detnet(np.zeros((1, side, side, 3), np.uint8))
        except Exception as e:   # onnxruntime's errors (wrong input name or shape) are no ValueError
            raise ValueError(f"DetNet model {name} does not take (N,{side},{side},3) crops: "
                             f"{str(e).splitlines()[0][:200]}") from None
    for finder, name, default in ((detector.finder, "finder", FINDER_PATH),
                                  (detector.grey_finder, "grey_finder", GREY_FINDER_PATH)):
        if finder is None:
            continue
        try:
            finder.find(np.zeros((480, 640, 3), np.uint8))
        except Exception as e:
            raise ValueError(f"hand finder model {params.get(name) or default} does not take a "
                             f"frame: {str(e).splitlines()[0][:200]}") from None


def start() -> tuple[Node, Callable[[Message], None]]:
    """The node, set up (topics, models), and its handler of one /camera/image message."""
    node = Node("detector", params=PARAMS)
    p = node.params
    # topics first, models second: the graph's other nodes see /hand/keypoints while the models
    # load and are connected when the first frame comes (else the first publish waits for them)
    node.subscribe("/camera/image", "Image", mode="lossless" if p["every_frame"] else "latest")
    node.advertise("/hand/keypoints", "HandKeypoints")
    detector = HandDetector.load(p["detnet"], p["finder"], threads=int(p["threads"]),
                                 grey_finder=p["grey_finder"], grey_detnet=p["grey_detnet"],
                                 side_detnet=p["side_detnet"],
                                 **{k: setting(k, p[k]) for k in TUNABLE})
    warm_up(detector, p)
    node.at_close(lambda: node.log.info("%d frames, %d finder runs, %d crops", detector.stats["frames"],
                                        detector.stats["finder_runs"], detector.stats["crops"]))

    def on_image(msg: Message) -> None:
        try:
            frame = frame_bgr(msg.data)
        except ValueError as e:
            node.log.warning("skipped an image: %s", e)
            return
        hands = detector.process(frame, msg.stamp_ns / 1e9)
        node.publish("/hand/keypoints", {"width": int(frame.shape[1]), "height": int(frame.shape[0]), "hands": hands},
                     stamp_ns=msg.stamp_ns, frame_id=msg.data["header"]["frame_id"])
    return node, on_image


def main() -> None:
    spin(start)   # its own loop; in a container, the executor calls the handler instead


if __name__ == "__main__":
    run(main)
