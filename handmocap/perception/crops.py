"""The square crops DetNet reads, cut from a frame and mapped back (no bus, no network).

A crop is a square of the frame, optionally turned (`angle`) and mirrored, resampled to
CROP x CROP px: `CropTransform` records the crop <-> frame mapping for 2D points and 3D
offsets; the helpers cut a track's next crop from its joints (`crop_for_joints`), a new
hand's from a found box (`crop_for_box`), and the variants a reading is averaged over
(`nearby_crops`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from handmocap.perception.hand_finder import square
from handmocap.perception.rotations import mirror_points

CROP = 128                  # px: the crop side DetNet reads when its file does not say (DetNetRunner.crop_side)
CROP_SCALE = 1.5            # crop side / side of the 21-joint box (synth: vertex box ~1.16x joint box, x 1.3)
MIN_CROP_SIDE = 24.0        # px in the frame
# (side factor, extra turn in degrees) of the crops a new track's reading is averaged over
# besides its own (`test_time_crops`): within the jitter DetNet was trained with
TEST_TIME_VARIANTS = ((0.9, 0.0), (1.1, 0.0), (1.0, -20.0), (1.0, 20.0), (0.95, -10.0), (1.05, 10.0))


@dataclass(frozen=True)
class CropTransform:
    """A square crop of the frame, turned by `angle`, resized to `size` px, optionally
    flipped left-right.

    The square has `side` frame px and its centre at c = (x0, y0) + (side - 1) / 2 (integers
    x0, y0: at angle 0 it covers frame pixels x0 .. x0+side-1). `angle` (radians) is the
    direction, clockwise from the frame's up, that becomes up in the crop: a hand leaning by
    `angle` appears upright. Pixel centres are at integer coordinates in both images
    (cv2.resize's convention):
        u_crop = (size - 1) / 2 + (size / side) R (u - c),  R = [[cos a, sin a], [-sin a, cos a]],
    then u_crop -> size - 1 - u_crop if mirrored. At angle 0 that is
        u_crop = (u - x0 + 0.5) * size / side - 0.5.
    """
    x0: int
    y0: int
    side: int
    size: int = CROP
    mirrored: bool = False
    angle: float = 0.0

    @classmethod
    def around(cls, centre, side, size=CROP, mirrored=False, angle=0.0):
        """The crop of about `side` px (at least MIN_CROP_SIDE) centred on `centre` (2,) px."""
        side = int(round(max(float(side), MIN_CROP_SIDE)))
        x0 = int(math.floor(centre[0] - (side - 1) / 2 + 0.5))
        y0 = int(math.floor(centre[1] - (side - 1) / 2 + 0.5))
        return cls(x0, y0, side, size, bool(mirrored), float(angle))

    @property
    def centre(self):
        """(2,) frame px of the crop's centre."""
        return np.array([self.x0 + (self.side - 1) / 2, self.y0 + (self.side - 1) / 2])

    @property
    def rotation(self):
        """(2,2) R: crop axes = R @ frame axes (the identity at angle 0)."""
        c, s = math.cos(self.angle), math.sin(self.angle)
        return np.array([[c, s], [-s, c]])

    @property
    def box(self):
        """(4,) x0, y0, x1, y1 frame px of the crop's outer edges (turned: the box around them)."""
        half = self.side / 2 * (abs(math.cos(self.angle)) + abs(math.sin(self.angle)))
        c = self.centre
        return np.array([c[0] - half, c[1] - half, c[0] + half, c[1] + half])

    def to_crop(self, uv):
        """(..., 2) frame px -> crop px."""
        uv = np.asarray(uv, dtype=np.float64)
        out = (uv - self.centre) @ (self.rotation.T * (self.size / self.side)) + (self.size - 1) / 2
        if self.mirrored:
            out[..., 0] = self.size - 1 - out[..., 0]
        return out

    def to_frame(self, uv_crop):
        """(..., 2) crop px -> frame px."""
        uv_crop = np.array(uv_crop, dtype=np.float64)
        if self.mirrored:
            uv_crop[..., 0] = self.size - 1 - uv_crop[..., 0]
        return (uv_crop - (self.size - 1) / 2) @ (self.rotation * (self.side / self.size)) + self.centre

    def to_frame_axes(self, xyz):
        """(..., 3) vectors in the crop's camera axes (unmirrored) -> the frame camera's:
        the turn about the optical axis undone."""
        xyz = np.array(xyz, dtype=np.float64)
        xyz[..., :2] = xyz[..., :2] @ self.rotation
        return xyz

    def cut(self, image):
        """(size,size,C) uint8 crop of `image` (H,W,C); outside the frame the border pixels
        are repeated. Cost is about independent of the crop's side: a crop at least twice
        the output size is first shrunk by k, the largest power of two that leaves at least
        `size` px (halvings by 2x2 means, in-frame part only, exact pixel mapping
        u_small + 0.5 = (u - x + 0.5) / k), then one bilinear warp (shrinking by less than 2).
        Powers of two because OpenCV's area shrink is vectorised for a factor of 2 alone:
        by 3 it costs 8x a halving, by 5 20x (docs/experiment_log.md, session 24)."""
        h, w = image.shape[:2]
        s = self.size / self.side                       # crop px per frame px
        k = 1 << max(0, int(1.0 / s).bit_length() - 1)
        src, ox, oy = image, 0, 0
        if k >= 2:                                      # the in-frame part (+ margin), whole k-blocks
            lo = self.box[:2] + 0.5                     # (x0, y0) at angle 0
            span = self.box[2] - self.box[0]
            ox, oy = max(int(math.floor(lo[0])) - k, 0) // k * k, max(int(math.floor(lo[1])) - k, 0) // k * k
            x1 = min(int(math.ceil(lo[0] + span)) + k, w)
            y1 = min(int(math.ceil(lo[1] + span)) + k, h)
            nx, ny = (x1 - ox) // k, (y1 - oy) // k
            if nx < 1 or ny < 1:                        # wholly outside: nearest frame pixels only
                k, ox, oy = 1, 0, 0
            else:
                src = image[oy:oy + ny * k, ox:ox + nx * k]
                for _ in range(k.bit_length() - 1):     # 2x2 means, k/2 ... 1 times: one k x k mean
                    src = cv2.resize(src, (src.shape[1] // 2, src.shape[0] // 2), interpolation=cv2.INTER_AREA)
        # frame u = k (u_src + 0.5) - 0.5 + o, then the crop mapping of the class doc
        A = self.rotation * s
        t = A @ (np.array([0.5 * k - 0.5 + ox, 0.5 * k - 0.5 + oy]) - self.centre) + (self.size - 1) / 2
        M = np.hstack([A * k, t[:, None]])
        if self.mirrored:                               # u_crop -> size - 1 - u_crop, inside the one warp
            M[0] = -M[0]
            M[0, 2] += self.size - 1
        return cv2.warpAffine(src, M, (self.size, self.size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def crop_to_frame_xyz(crop, xyz):
    """(..., 3) DetNet 3D read on `crop` (right-hand, crop axes) -> the frame camera's axes."""
    return crop.to_frame_axes(mirror_points(xyz) if crop.mirrored else xyz)


def frame_to_crop_xyz(crop, xyz):
    """Inverse of crop_to_frame_xyz: (..., 3) frame-camera axes -> as DetNet reads `crop`."""
    xyz = np.array(xyz, dtype=np.float64)
    xyz[..., :2] = xyz[..., :2] @ crop.rotation.T
    return mirror_points(xyz) if crop.mirrored else xyz


def hand_angle(uv):
    """Direction (radians, clockwise from the frame's up) from the wrist (0) to the middle
    finger's base (9) of joints uv (..., 21, 2) px: the turn that shows the hand upright."""
    v = np.asarray(uv, dtype=np.float64)[..., 9, :] - np.asarray(uv, dtype=np.float64)[..., 0, :]
    return np.arctan2(v[..., 0], -v[..., 1])


PALM_ANGLE_JOINTS = (0, 5, 9, 13, 17)   # the joints palm_angle reads


def knuckle_line_normal(uv):
    """(..., 2) px: the knuckle line (index base 5 -> little base 17) of joints uv (..., 21, 2)
    turned a quarter turn, toward the knuckles' side of the wrist; as long as the palm is wide."""
    uv = np.asarray(uv, dtype=np.float64)
    across = uv[..., 17, :] - uv[..., 5, :]
    normal = np.stack([-across[..., 1], across[..., 0]], axis=-1)
    toward = uv[..., [5, 9, 13, 17], :].mean(axis=-2) - uv[..., 0, :]
    return np.where(np.sum(normal * toward, axis=-1, keepdims=True) < 0, -normal, normal)


def palm_angle(uv):
    """Direction (radians, as hand_angle) the palm points to, from joints uv (..., 21, 2) px: the
    wrist -> middle knuckle (0 -> 9) plus knuckle_line_normal, both in px. With the fingers toward
    or away from the camera the first is short and its direction noise, the second still as long
    as the palm is wide (DetNet's `turn_by` "palm")."""
    uv = np.asarray(uv, dtype=np.float64)
    v = uv[..., 9, :] - uv[..., 0, :] + knuckle_line_normal(uv)
    return np.arctan2(v[..., 0], -v[..., 1])


# what "upright" is, by name: the detector's `turn_by` and `handtrain detnet --upright-by` (one table)
HAND_ANGLES = {"wrist_knuckle": hand_angle, "palm": palm_angle}


def angle_apart(a, b):
    """|a - b| of two angles (radians; scalars or arrays), wrapped to [0, pi]."""
    return np.abs((np.subtract(a, b) + np.pi) % (2 * np.pi) - np.pi)


def head_angle_in_frame(crop, cos_sin):
    """The hand's angle in the frame (radians, as hand_angle) from DetNet's angle head on `crop`:
    cos_sin (2,) = (cos, sin) of its angle in the crop (training/angle_head.py)."""
    a = math.atan2(float(cos_sin[1]), float(cos_sin[0]))
    centre = np.full(2, (crop.size - 1) / 2)
    wrist, knuckle = crop.to_frame(np.stack([centre, centre + 10.0 * np.array([math.sin(a), -math.cos(a)])]))
    v = knuckle - wrist
    return math.atan2(v[0], -v[1])


def rounded_turn(angle, upright_step):
    """angle (radians) rounded to whole steps of upright_step degrees (0 or None: as it is)."""
    if not upright_step:
        return angle
    step = math.radians(float(upright_step))
    return round(angle / step) * step


def crop_for_joints(uv, mirrored=False, scale=CROP_SCALE, upright_step=None, size=CROP, angle=None):
    """The DetNet crop (`size` px) of a hand whose 2D joints are uv (21,2) frame px: the square
    around their box times `scale`. upright_step (degrees): the crop turned by hand_angle rounded to
    whole steps of it (90: quarter turns; 0: any angle), the box taken in the turned axes (as
    MediaPipe cuts its landmark crops); None: never turned. angle (radians, as hand_angle): the
    hand's angle from elsewhere (DetNet's angle head), rounded the same way, instead of the joints'."""
    if upright_step is None:
        angle = 0.0
    elif angle is None:
        angle = float(hand_angle(uv)) if np.all(np.isfinite(uv[[0, 9]])) else 0.0
    angle = rounded_turn(float(angle), upright_step)
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, s], [-s, c]])
    turned = uv @ R.T
    lo, hi = np.nanmin(turned, axis=0), np.nanmax(turned, axis=0)
    return CropTransform.around(R.T @ ((lo + hi) / 2), float(np.max(hi - lo)) * scale, size, mirrored=mirrored,
                                angle=angle)


def square_box(uv):
    """(4,) x0, y0, x1, y1 of the square around joints uv (21,2) (the finder's box)."""
    return square(np.concatenate([np.nanmin(uv, axis=0), np.nanmax(uv, axis=0)]))


def nearby_crops(crop, k):
    """The first `k` TEST_TIME_VARIANTS of a CropTransform: the same hand a little larger,
    smaller or turned (same centre and mirroring)."""
    return [CropTransform.around(crop.centre, crop.side * scale, crop.size, mirrored=crop.mirrored,
                                 angle=crop.angle + math.radians(turn)) for scale, turn in TEST_TIME_VARIANTS[:k]]


def crop_for_box(box, mirrored=False, scale=CROP_SCALE, size=CROP):
    """The DetNet crop (`size` px) of a hand whose joint box is (4,) x0, y0, x1, y1 frame px."""
    box = np.asarray(box, dtype=np.float64)
    return CropTransform.around((box[:2] + box[2:]) / 2, float(np.max(box[2:] - box[:2])) * scale, size,
                                mirrored=mirrored)


def box_overlap_of_smaller(box, boxes):
    """(M,) intersection of `box` (4,) with each of `boxes` (M,4), over the smaller area."""
    x0, y0 = np.maximum(box[0], boxes[:, 0]), np.maximum(box[1], boxes[:, 1])
    x1, y1 = np.minimum(box[2], boxes[:, 2]), np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = lambda b: np.maximum((b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1]), 1e-9)   # noqa: E731
    return inter / np.minimum(area(box), area(boxes))
