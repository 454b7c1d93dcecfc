"""Hand finder: every hand in a whole frame, with no prior (models/finder.onnx).

A tiny CenterNet-style network on the frame letterboxed into S x S (aspect kept, grey
border; S is the model file's input side, INPUT_SIZE for the shipped finder). On a
STRIDE-px grid it predicts, per cell, channel
    0  hand-centre heatmap logit (centre of the hand's 21-joint box),
    1-2 sub-cell offset of the centre (cells, 0..1),
    3  log(box side / S), box side = max(width, height) of the joint box,
    4  handedness logit: the hand appears as a right hand.
Read-out: 3x3 max-pool peaks above `threshold`, best first, non-maximum suppressed by
box overlap. It runs when the detector has lost a track or every N frames, never per hand.

>>> finder = HandFinder.load()
>>> hands = finder.find(frame_bgr)      # [FoundHand(box, score, right_prob), ...]

Letterbox mapping (pixel centres at integer coordinates, as cv2.resize):
    u_in = (u + 0.5) * scale - 0.5 + pad_x, and the same for v with pad_y.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.onnx_models import open_session

INPUT_SIZE = 160
STRIDE = 8
BORDER_VALUE = 114
DEFAULT_PATH = Path(__file__).resolve().parents[2] / "models" / "finder.onnx"
# trained with a fifth of its frames in grey: the detector runs it on grey frames (is_grey),
# where the colour-trained finder finds about a quarter of the hands (docs/models_history.md)
GREY_PATH = DEFAULT_PATH.with_name("finder_grey.onnx")


@dataclass
class FoundHand:
    """One hand found in a frame. box (4,) x0, y0, x1, y1 frame px of its joint box (a
    square of side = max side); score: peak probability; right_prob: probability that it
    appears as a right hand."""
    box: np.ndarray
    score: float
    right_prob: float


@dataclass(frozen=True)
class Letterbox:
    """Frame -> network input: u_in = (u + 0.5) * scale - 0.5 + pad (per axis)."""
    scale_x: float
    scale_y: float
    pad_x: int
    pad_y: int

    def to_input(self, uv):
        uv = np.asarray(uv, dtype=np.float64)
        return np.stack([(uv[..., 0] + 0.5) * self.scale_x - 0.5 + self.pad_x,
                         (uv[..., 1] + 0.5) * self.scale_y - 0.5 + self.pad_y], axis=-1)

    def to_frame(self, uv_in):
        uv_in = np.asarray(uv_in, dtype=np.float64)
        return np.stack([(uv_in[..., 0] - self.pad_x + 0.5) / self.scale_x - 0.5,
                         (uv_in[..., 1] - self.pad_y + 0.5) / self.scale_y - 0.5], axis=-1)


def letterbox(image, size=INPUT_SIZE):
    """Resize (H,W,C) uint8 into (size,size,C) keeping the aspect, centred on a grey
    border. Returns (image, Letterbox). (The one-step area shrink is what the finders were
    trained on: shrinking by halvings first, 2.6x faster on a 1280x720 frame and within 2
    levels of it, doubled the v9 finder's false hands on the held-back clips, session 41.)"""
    h, w = image.shape[:2]
    s = size / max(h, w)
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    resized = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    px, py = (size - nw) // 2, (size - nh) // 2
    out = np.full((size, size) + image.shape[2:], BORDER_VALUE, np.uint8)
    out[py:py + nh, px:px + nw] = resized
    return out, Letterbox(nw / w, nh / h, px, py)


def box_iou(a, b):
    """IoU of boxes a (N,4) and b (M,4), x0 y0 x1 y1 -> (N,M)."""
    a, b = np.asarray(a, np.float64).reshape(-1, 4), np.asarray(b, np.float64).reshape(-1, 4)
    x0 = np.maximum(a[:, None, 0], b[None, :, 0])
    y0 = np.maximum(a[:, None, 1], b[None, :, 1])
    x1 = np.minimum(a[:, None, 2], b[None, :, 2])
    y1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def square(boxes):
    """(..., 4) boxes -> the squares of side max(width, height) on the same centres (the
    finder's box around a hand's 21-joint box)."""
    c, side = (boxes[..., :2] + boxes[..., 2:]) / 2, np.max(boxes[..., 2:] - boxes[..., :2], -1, keepdims=True)
    return np.concatenate([c - side / 2, c + side / 2], -1)


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


def decode(maps, threshold=0.3, max_hands=2, nms_iou=0.3, input_size=INPUT_SIZE):
    """Network output (5, S/STRIDE, S/STRIDE) of an input_size S finder -> list of (box (4,)
    input px, score, right_prob), best first."""
    heat = sigmoid(maps[0])
    pooled = cv2.dilate(heat.astype(np.float32), np.ones((3, 3), np.uint8))
    peaks = np.argwhere((heat >= pooled - 1e-7) & (heat >= threshold))
    order = np.argsort(-heat[peaks[:, 0], peaks[:, 1]])
    found = []
    for gy, gx in peaks[order]:
        cx = (gx + maps[1, gy, gx]) * STRIDE - 0.5
        cy = (gy + maps[2, gy, gx]) * STRIDE - 0.5
        side = float(np.exp(maps[3, gy, gx]) * input_size)
        box = np.array([cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2])
        if found and box_iou(box, np.array([f[0] for f in found])).max() > nms_iou:
            continue
        found.append((box, float(heat[gy, gx]), float(sigmoid(maps[4, gy, gx]))))
        if len(found) == max_hands:
            break
    return found


def is_grey(image_bgr, tolerance=8, step=7):
    """Whether a BGR frame (H,W,3) uint8 is grey (a mono or IR camera, a black-and-white
    video): its channels differ by at most `tolerance` on every `step`-th pixel of every
    `step`-th row (a colour camera's frames are never that close; video chroma and JPEG
    rounding keep a grey frame's within a few levels)."""
    sample = image_bgr[::step, ::step].astype(np.int16)
    return bool(np.abs(sample[..., 0] - sample[..., 1]).max() <= tolerance
                and np.abs(sample[..., 1] - sample[..., 2]).max() <= tolerance)


def greyed(image_bgr):
    """(...,H,W,3) uint8 BGR -> the same in grey, three equal channels (OpenCV's luma; pass
    RGB images reversed, `greyed(rgb[..., ::-1])`): a mono camera's view, for training and
    checks on grey frames."""
    flat = image_bgr.reshape(-1, *image_bgr.shape[-3:])
    g = np.stack([cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_BGR2GRAY) for f in flat]) if len(flat) \
        else np.zeros(flat.shape[:-1], np.uint8)
    return np.repeat(g[..., None], 3, -1).reshape(image_bgr.shape)


def to_input_tensor(images_rgb, out=None):
    """(N,S,S,3) uint8 RGB -> (N,3,S,S) float32 in [0,1] (into `out` when given: a fresh array
    of this size costs more in page faults than the conversion)."""
    return np.divide(np.asarray(images_rgb).transpose(0, 3, 1, 2), np.float32(255), out=out, dtype=np.float32)


class HandFinder:
    """models/finder.onnx on onnxruntime (CPU). threshold: minimum peak probability. The
    frame is letterboxed into the file's input side (`size`: 160 for the shipped finder)."""

    def __init__(self, session, threshold=0.3, max_hands=2):
        self.session = session
        self.input_name = session.get_inputs()[0].name
        side = session.get_inputs()[0].shape[-1]
        self.size = side if isinstance(side, int) else INPUT_SIZE
        self.threshold, self.max_hands = threshold, max_hands
        self._input = None        # the network input, kept between runs (to_input_tensor)

    @classmethod
    def load(cls, path=None, threads=1, **kwargs):
        return cls(open_session(path or DEFAULT_PATH, "hand finder", "handtrain finder", threads), **kwargs)

    def raw(self, image_bgr):
        """(5, size/STRIDE, size/STRIDE) network output for one BGR frame, and its Letterbox."""
        boxed, lb = letterbox(image_bgr, self.size)
        if self._input is None or self._input.shape[-1] != self.size:
            self._input = np.empty((1, 3, self.size, self.size), np.float32)
        # OpenCV's colour conversion: a tenth of numpy's strided copy of reversed channels
        x = to_input_tensor(cv2.cvtColor(boxed, cv2.COLOR_BGR2RGB)[None], out=self._input)
        return self.session.run(None, {self.input_name: x})[0][0], lb

    def find(self, image_bgr, threshold=None, max_hands=None):
        """Hands in a BGR frame (H,W,3) uint8, best first: list of FoundHand (frame px).
        (OpenCV and onnxruntime let go of the GIL while they work: it can run beside other work.)"""
        maps, lb = self.raw(image_bgr)
        out = []
        for box, score, right in decode(maps, self.threshold if threshold is None else threshold,
                                        self.max_hands if max_hands is None else max_hands, input_size=self.size):
            corners = lb.to_frame(box.reshape(2, 2)).reshape(4)
            out.append(FoundHand(corners, score, right))
        return out
