"""Annotated camera frames: the 2D skeleton, labels, the posed hand mesh over the camera view
and a side view of it. Plain functions over numpy images (no bus); the `visualizer` node is a
thin loop around `Overlay.draw`.

Images are BGR (H,W,3) uint8 as OpenCV uses them; K is the (3,3) pinhole matrix in pixels;
3D points are metres in the OpenCV camera frame (x right, y down, z forward).

Where the mesh comes from (handmocap.perception.pose): a HandPose hand carries the right-hand model's
global bone quaternions `quat` (21,4), its shape `beta` (10,) and the camera-frame joints
`xyz` (21,3) = `root` + (model joints - model joint 9), mirrored in x for a left hand. So
`HandModel.forward(quat, beta, handedness)` gives vertices and joints in the model frame, whose
axes are the camera's, and one translation `root - joints[9]` puts both in the camera frame:
the mesh's joints then coincide with the published `xyz` (pose.hand_mesh). Lens distortion is
ignored, as the ik node's translation ignores it: the mesh is drawn with K alone.
"""
from __future__ import annotations

import cv2
import numpy as np

from handmocap.perception.camera_info import project
from handmocap.perception.hand_model import HandModel
from handmocap.perception.pose import hand_certainty, hand_mesh
from handmocap.perception.skeleton import BONES

# one colour per finger (BGR): thumb, index, middle, ring, little
FINGER_COLOURS = ((60, 60, 255), (60, 200, 60), (255, 160, 40), (220, 60, 220), (40, 220, 255))
WRIST_COLOUR = (255, 255, 255)
# mesh colour per handedness (RGB in [0,1], the renderer's convention): a light blue right hand,
# a light green left hand, both far from skin tones so the overlay reads over a real hand
MESH_COLOURS = {"right": (0.45, 0.7, 1.0), "left": (0.5, 0.95, 0.55)}
MESH_DEPTH_M = (0.05, 5.0)               # roots outside this range are failed translations: no mesh
SIDE_BACKGROUND = (0.16, 0.16, 0.18)     # RGB in [0,1]
SIDE_ANGLE_DEG = 90.0                    # the side view looks from the camera's right
SIDE_SPAN_M = 0.4                        # side view: metres across the inset (widened to fit hands)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def bone_colour(joint: int) -> tuple[int, int, int]:
    """BGR colour of the finger that joint (1..20) belongs to; the wrist's for joint 0."""
    return FINGER_COLOURS[(joint - 1) // 4] if joint > 0 else WRIST_COLOUR


def draw_skeleton(img, uv, confidence=None, min_confidence=0.3, thickness=2, radius=3):
    """Draw a hand's 21 joints uv (21,2) px on img (BGR, in place): bones coloured per finger,
    joints filled, hollow where confidence (21,) < min_confidence. Non-finite joints are
    skipped. Returns img."""
    uv = np.asarray(uv, dtype=np.float64)
    ok = np.all(np.isfinite(uv), axis=1)
    shift = 4                                     # sub-pixel coordinates for cv2 (1/16 px)
    pts = np.round(np.where(ok[:, None], uv, 0) * (1 << shift)).astype(np.int64)
    p = lambda j: (int(pts[j, 0]), int(pts[j, 1]))
    for parent, child in BONES:
        if ok[parent] and ok[child]:
            cv2.line(img, p(parent), p(child), bone_colour(child), thickness, cv2.LINE_AA, shift)
    for j in np.flatnonzero(ok):
        filled = confidence is None or confidence[j] >= min_confidence
        cv2.circle(img, p(j), radius << shift, bone_colour(j), -1 if filled else 1, cv2.LINE_AA, shift)
    return img


def draw_points(img, uv, colour=(255, 255, 255), radius=2):
    """Small hollow circles at uv (N,2) px (e.g. the projected 3D joints), in place."""
    for u, v in np.asarray(uv, dtype=np.float64):
        if np.isfinite(u) and np.isfinite(v):
            cv2.circle(img, (int(round(u)), int(round(v))), radius, colour, 1, cv2.LINE_AA)
    return img


def hand_label(hand: dict) -> str:
    """'right 0.73 #3' for a HandKeypoints / HandPose hand: handedness, how sure the detector
    is of its joints (pose.hand_certainty: the mean heatmap peak), track id."""
    return f"{hand['handedness']} {hand_certainty(hand):.2f} #{int(hand['track_id'])}"


def draw_label(img, text, anchor, colour=(255, 255, 255), scale=0.5):
    """Text on a dark box, its bottom-left corner at anchor (x, y) px, kept inside img."""
    (tw, th), base = cv2.getTextSize(text, FONT, scale, 1)
    h, w = img.shape[:2]
    x = int(np.clip(anchor[0], 0, max(w - tw - 4, 0)))
    y = int(np.clip(anchor[1], th + 4, h - base - 2))
    cv2.rectangle(img, (x, y - th - 4), (x + tw + 4, y + base + 1), (30, 30, 30), -1)
    cv2.putText(img, text, (x + 2, y - 1), FONT, scale, colour, 1, cv2.LINE_AA)
    return img


def mesh_colour(hand: dict) -> tuple[float, float, float]:
    """RGB in [0,1] of a hand's mesh, by handedness."""
    return MESH_COLOURS.get(hand["handedness"], MESH_COLOURS["right"])


def composite(frame, rgb, depth, alpha=0.6):
    """frame (H,W,3) BGR uint8 with a rendering rgb (H,W,3) RGB uint8 alpha-blended where its
    depth (H,W) > 0 (a surface was drawn). Returns a new BGR image."""
    out = frame.copy()
    mask = depth > 0
    out[mask] = (frame[mask] * (1.0 - alpha) + rgb[mask][:, ::-1] * alpha + 0.5).astype(np.uint8)
    return out


def side_view_transform(points, angle_deg=SIDE_ANGLE_DEG, span_m=SIDE_SPAN_M, distance_m=1.0):
    """The rigid map of the side view for a scene whose 3D points (N,3) (camera frame) are
    given: a virtual camera `distance_m` from their centre, orbited `angle_deg` about the
    camera's vertical axis (90: looking from the camera's right, so depth runs left to right
    in the inset, the real camera on the left). Returns (R (3,3), t (3,), span metres) with
    p_side = R p + t; span is `span_m`, widened to fit the points."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre = 0.5 * (points.min(0) + points.max(0)) if len(points) else np.zeros(3)
    a = np.radians(angle_deg)
    # rows: the side camera's axes in the camera frame; at 90 deg x' = z (depth runs left to
    # right), y' = y, z' = -x (it looks from the camera's right towards its left)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    local = (points - centre) @ R.T
    extent = 2.2 * np.abs(local[:, :2]).max() if len(points) else 0.0
    return R, np.array([0.0, 0.0, distance_m]) - R @ centre, max(span_m, extent)


def side_K(size: int, span_m: float, distance_m: float = 1.0):
    """(3,3) K of a square side-view inset `size` px showing `span_m` metres at `distance_m`."""
    f = size * distance_m / span_m
    c = (size - 1) / 2.0
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


class Overlay:
    """Draws annotated frames; owns the mesh renderers (made once per frame size, then reused).

    >>> overlay = Overlay()
    >>> annotated = overlay.draw(frame_bgr, K, pose_hands, keypoint_hands)

    mesh: render the posed hand mesh (needs OpenGL through EGL); alpha: its opacity over the
    frame; side: size of the side-view inset as a fraction of the frame's shorter side (0: none);
    joints3d: also mark the projected 3D joints `xyz` (small white circles).
    """

    def __init__(self, model: HandModel | None = None, mesh=True, alpha=0.6, side=0.33, joints3d=True):
        self.model = model if model is not None else HandModel.load()
        self.mesh, self.alpha, self.side, self.joints3d = bool(mesh), float(alpha), float(side), bool(joints3d)
        self._renderers = {}      # "main"/"side" -> MeshRenderer of the current frame size

    def _renderer(self, key: str, width: int, height: int):
        r = self._renderers.get(key)
        if r is None or (r.width, r.height) != (width, height):
            if r is not None:
                r.release()
            self._renderers[key] = r = make_renderer(width, height)
        return r

    def _render(self, key: str, width: int, height: int, meshes, K, **kw):
        """One MeshRenderer.render (each renderer draws in its own GL context)."""
        return self._renderer(key, width, height).render(meshes, K, **kw)

    def check(self, width=640, height=480) -> None:
        """Make the renderers now (fails with RuntimeError naming the cause, e.g. no EGL)."""
        if self.mesh:
            self._renderer("main", width, height)
            if self.side_size(width, height):
                self._renderer("side", *(self.side_size(width, height),) * 2)

    def side_size(self, width: int, height: int) -> int:
        return int(self.side * min(width, height)) if self.mesh else 0

    def draw(self, frame, K, pose_hands=(), keypoint_hands=()):
        """Annotated copy of frame (H,W,3) BGR uint8: the mesh of every pose hand whose root is
        MESH_DEPTH_M away (one render for all), the 2D skeleton of every keypoints hand (of a
        pose hand without keypoints: its uv), the projected 3D joints, labels, the side view.
        K (3,3) px; pose_hands: HandPose hands; keypoint_hands: HandKeypoints hands (same frame)."""
        h, w = frame.shape[:2]
        K = np.asarray(K, dtype=np.float64)
        meshes = [hand_mesh(self.model, hand) + (hand,) for hand in pose_hands
                  if self.mesh and np.all(np.isfinite(hand["root"]))
                  and MESH_DEPTH_M[0] < hand["root"][2] < MESH_DEPTH_M[1]]
        out = frame.copy()
        if meshes:
            rgb, depth = self._render("main", w, h, [(v, f, mesh_colour(hand)) for v, f, _, hand in meshes], K)
            out = composite(frame, rgb, depth, self.alpha)
        pose_by_track = {hand["track_id"]: hand for hand in pose_hands}
        seen = {hand["track_id"] for hand in keypoint_hands}
        skeletons = list(keypoint_hands) + [hand for hand in pose_hands if hand["track_id"] not in seen]
        for hand in skeletons:
            draw_skeleton(out, hand["uv"], hand.get("confidence"))
        if self.joints3d:
            for hand in pose_hands:
                draw_points(out, project(K, hand["xyz"]))
        for hand in skeletons:            # labels last: on top of every skeleton
            uv = np.asarray(hand["uv"], dtype=np.float64)
            uv = uv[np.all(np.isfinite(uv), axis=1)]
            best = pose_by_track.get(hand["track_id"], hand)
            if len(uv):
                draw_label(out, hand_label(best),
                           (uv[:, 0].min(), uv[:, 1].min() - 6))
        size = self.side_size(w, h)
        if size >= 32:
            out[h - size - 8:h - 8, w - size - 8:w - 8] = self.side_view(meshes, size)
        return out

    def side_view(self, meshes, size: int):
        """(size,size,3) BGR inset: meshes [(vertices, faces, joints, hand)] seen from the side
        (side_view_transform), with their 3D skeletons; a label says where the camera is."""
        points = np.concatenate([v for v, *_ in meshes]) if meshes else np.zeros((0, 3))
        R, t, span = side_view_transform(points)
        K = side_K(size, span)
        if meshes:
            rgb, _ = self._render("side", size, size, [(v @ R.T + t, f, mesh_colour(hand)) for v, f, _, hand in meshes],
                                  K, background=SIDE_BACKGROUND)
            inset = np.ascontiguousarray(rgb[..., ::-1])
            for _, _, joints, _ in meshes:
                draw_skeleton(inset, project(K, joints @ R.T + t), thickness=1, radius=1)
        else:
            inset = np.empty((size, size, 3), np.uint8)
            inset[:] = (np.array(SIDE_BACKGROUND[::-1]) * 255).astype(np.uint8)
        cv2.putText(inset, "side, camera at left", (4, 14), FONT, 0.4, (220, 220, 220), 1, cv2.LINE_AA)
        cv2.rectangle(inset, (0, 0), (size - 1, size - 1), (200, 200, 200), 1)
        return inset

    def release(self) -> None:
        for r in self._renderers.values():
            r.release()
        self._renderers.clear()


def make_renderer(width: int, height: int):
    """A MeshRenderer, or RuntimeError with one line naming why OpenGL is not available."""
    try:
        from handmocap.perception.render import MeshRenderer
        return MeshRenderer(width, height)
    except ImportError as e:
        raise RuntimeError(f"cannot render the hand mesh: {e} (install the viz extra: pip install -e '.[viz]'; "
                           f"or set mesh:=false)") from None
    except Exception as e:   # moderngl/glcontext raise bare Exceptions ("libEGL.so.1 not loaded")
        raise RuntimeError(f"cannot render the hand mesh: no OpenGL through EGL ({e}); on Debian/Ubuntu: "
                           f"apt-get install libegl1 libgl1-mesa-dri libegl-mesa0; or set mesh:=false") from None
