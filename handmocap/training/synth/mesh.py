"""The hand mesh as the image engine draws it: a longer forearm, static material
attributes per vertex, and batched float32 skinning with normals.

The bundled model ends 13 cm up the forearm with an open, slanted cut. In a crop that
frames the hand 1.3x the cut would show, so `SynthHand` extends the arm with rings of
new vertices to ~40 cm from the wrist (closed with a cap), skinned rigidly to the wrist
frame, whose shape offsets copy those of the cut's nearest vertex.

Static per-vertex attributes (model frame, rest pose), read by the shader:
* `rest` (V,3) metres: drives procedural skin noise and the sleeve boundary (rest y);
* `material` (V,4): nail weight, palm-side weight, knuckle weight, hand weight
  (1 on hand and fingers, falling to 0 a few cm up the forearm), each in [0,1].
"""
import numpy as np

from handmocap.perception.joint_limits import FINGER_JOINTS, local_frames
from handmocap.perception.kinematics import forward_kinematics, frames_to_bone_rotations, frames_to_relative, POSE16_TO_MANO
from handmocap.perception.render import vertex_normals
from handmocap.perception.skeleton import FINGER_TIPS, NON_TIP_JOINTS
from .decimate import decimate

FOREARM_END_Y = 0.40         # metres from the wrist, along +y (model frame) where the arm ends
HAND_REGION_Y = 0.02         # rest vertices with y below this count as "hand" (box, hand weight)
_NAIL_LENGTH = 0.011         # metres along the distal phalanx, from its tip
_FEATURE_COST = 3e-11      # m^4 (quadric units: area x distance^2) per unit of material difference^2
_THUMB_DORSAL = np.array([0.75, 0.0, 0.66])    # model-frame direction the thumbnail faces (approx.)


def boundary_loop(faces):
    """Vertex ids (L,) of the single open boundary loop of a mesh, in walking order."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    border = edges[counts[inverse.ravel()] == 1]           # directed, as the faces run
    nxt = dict(zip(border[:, 0].tolist(), border[:, 1].tolist()))
    start = int(border[0, 0])
    loop = [start]
    while nxt[loop[-1]] != start:
        loop.append(nxt[loop[-1]])
        if len(loop) > len(border):
            raise ValueError("mesh boundary is not one simple loop")
    if len(loop) != len(border):
        raise ValueError(f"mesh has {len(border)} boundary edges but the loop has {len(loop)}")
    return np.array(loop)


class SynthHand:
    """A HandModel prepared for fast rendering.

    Arrays (V = model vertices + forearm extension):
    v_template (V,3), shapedirs (V*3, B) float32 (flattened for one matmul),
    weights (V,16) float32, faces (F,3) int32, rest_normals (V,3), material (V,4),
    part (V,) int: the joint frame (index into NON_TIP_JOINTS) that moves the vertex most,
    hand_vertex (V,) bool (hand and fingers, for the hand box).
    """

    def __init__(self, model, rings=(0.22, 0.31, FOREARM_END_Y), widen=0.15, draw_faces=1500):
        self.model = model
        v, faces = model.v_template, model.faces
        loop = boundary_loop(faces)
        ring_n = len(loop)
        cut = v[loop]
        centre = cut.mean(0)
        new_v, new_sd = [], []
        for k, y_end in enumerate(rings):
            grow = 1.0 + widen * (y_end - cut[:, 1].mean()) / (FOREARM_END_Y - cut[:, 1].mean())
            ring = centre + (cut - centre) * grow
            ring[:, 1] = y_end
            new_v.append(ring)
            new_sd.append(model.shapedirs[loop])
        cap_centre = np.array([[centre[0], rings[-1], centre[2]]])
        new_v = np.concatenate(new_v + [cap_centre])
        new_sd = np.concatenate(new_sd + [model.shapedirs[loop].mean(0, keepdims=True)])
        base = len(v)
        # the loop runs the way its faces run; new quads must keep the winding outward
        rings_ids = [loop] + [base + k * ring_n + np.arange(ring_n) for k in range(len(rings))]
        tri = []
        for a, b in zip(rings_ids[:-1], rings_ids[1:]):
            a2, b2 = np.roll(a, -1), np.roll(b, -1)
            tri += [np.stack([a2, a, b], 1), np.stack([a2, b, b2], 1)]
        cap = base + len(rings) * ring_n
        last = rings_ids[-1]
        tri.append(np.stack([np.roll(last, -1), last, np.full(ring_n, cap)], 1))
        self.faces = np.concatenate([faces] + tri).astype(np.int32)
        self.v_template = np.concatenate([v, new_v])
        shapedirs = np.concatenate([model.shapedirs, new_sd])                  # (V,3,B)
        self.num_betas = shapedirs.shape[-1]
        self.shapedirs = shapedirs.reshape(-1, self.num_betas).astype(np.float32)
        extra_w = np.zeros((len(new_v), 16))
        extra_w[:, 0] = 1.0
        self.weights = np.concatenate([model.weights, extra_w]).astype(np.float32)
        self.posedirs = None if model.posedirs is None else np.concatenate(
            [model.posedirs, np.zeros((len(new_v),) + model.posedirs.shape[1:])])
        self.rest_normals = vertex_normals(self.v_template, self.faces)
        if np.mean(np.sum(self.rest_normals * (self.v_template - self.v_template.mean(0)), 1) > 0) < 0.5:
            self.faces = self.faces[:, ::-1].copy()             # keep normals pointing outwards
            self.rest_normals = -self.rest_normals
        self.num_vertices = len(self.v_template)
        self.hand_vertex = self.v_template[:, 1] < HAND_REGION_Y
        self.material = self._material().astype(np.float32)
        self.part = np.argmax(self.weights, axis=1).astype(np.int32)    # (V,) dominant joint frame
        self.full_vertices, self.full_faces = self.v_template, self.faces
        if draw_faces and draw_faces < len(self.faces):
            self._decimate(draw_faces)

    def _decimate(self, target_faces):
        """Keep a subset of the vertices (decimate.py) and re-triangulate: every
        per-vertex array is sliced, so kept vertices skin exactly as in the full mesh;
        normals stay the full mesh's (smooth shading of the fine surface)."""
        kept, self.faces = decimate(self.v_template, self.faces, target_faces, labels=self.part,
                                    features=self.material, feature_cost=_FEATURE_COST)
        self.kept = kept
        self.v_template = self.v_template[kept]
        b = self.num_betas
        self.shapedirs = self.shapedirs.reshape(-1, 3, b)[kept].reshape(-1, b)
        if self.posedirs is not None:
            self.posedirs = self.posedirs[kept]
        for name in ("weights", "rest_normals", "material", "part", "hand_vertex"):
            setattr(self, name, getattr(self, name)[kept])
        self.num_vertices = len(kept)

    # ------------------------------------------------------------ static attributes
    def _material(self):
        """(V,4) nail, palm-side, knuckle and hand weights in [0,1] from rest geometry."""
        v, n, joints = self.v_template, self.rest_normals, self.model.j_template
        frames, _ = local_frames(joints)
        nail = np.zeros(len(v))
        knuckle = np.zeros(len(v))
        palm = np.zeros(len(v))
        for tip in FINGER_TIPS:
            dip = tip - 1
            f, _, t = frames[FINGER_JOINTS.index(dip)].T
            dorsal = np.cross(t, f)
            if tip == 4:
                dorsal = _THUMB_DORSAL - (_THUMB_DORSAL @ t) * t
            dorsal /= np.linalg.norm(dorsal)
            side = np.cross(t, dorsal)
            tip_end = joints[dip] + t * ((self.model.v_template[self.model.tip_vertex_ids[FINGER_TIPS.index(tip)]]
                                          - joints[dip]) @ t)
            rel = v - tip_end
            along = rel @ t                                     # <= 0 behind the tip
            across = np.abs(rel @ side)
            up = n @ dorsal
            width = 0.0072 if tip == 4 else 0.006 if tip != 20 else 0.005
            length = _NAIL_LENGTH * (1.2 if tip == 4 else 1.0 if tip != 20 else 0.85)
            w = (_smooth(-length - 0.001, -length + 0.002, along) * _smooth(0.0015, -0.001, along)
                 * _smooth(width, width * 0.7, across) * _smooth(0.25, 0.55, up))
            w *= (np.linalg.norm(rel, axis=1) < 0.03)
            nail = np.maximum(nail, w)
        for j in NON_TIP_JOINTS[1:]:
            if j in (1,):
                continue
            f, _, t = frames[FINGER_JOINTS.index(j)].T
            dorsal = np.cross(t, f) if j > 4 else _THUMB_DORSAL - (_THUMB_DORSAL @ t) * t
            dorsal /= np.linalg.norm(dorsal)
            d = np.linalg.norm(v - joints[j], axis=1)
            knuckle = np.maximum(knuckle, _smooth(0.014, 0.006, d) * _smooth(0.2, 0.7, n @ dorsal))
            palm = np.maximum(palm, _smooth(0.018, 0.008, d) * _smooth(0.0, -0.6, n @ dorsal))
        # palm side of palm and fingers: normals facing -z (away from the back of the hand)
        palm = np.maximum(palm, _smooth(-0.1, -0.6, n[:, 2]) * _smooth(0.03, -0.01, v[:, 1]))
        hand = _smooth(0.06, 0.0, v[:, 1])
        return np.stack([nail, palm, knuckle * (1 - nail), hand], axis=1)

    def joint_radii(self, directions=24):
        """(21,) metres: how deep each rest joint lies under the surface, seen from the side.

        For directions perpendicular to the joint's bone, the nearest vertex within a
        25 degree cone gives the surface distance; the largest over directions is the
        radius. A joint whose pixel shows its own hand no nearer than depth - radius is
        visible (scene.joint_visibility).
        """
        v, joints = self.full_vertices, self.model.j_template
        radii = np.zeros(len(joints))
        for j in range(len(joints)):
            child = j + 1 if j not in FINGER_TIPS and j != 0 else None
            t = joints[9] - joints[0] if j == 0 else (joints[child] - joints[j] if child else joints[j] - joints[j - 1])
            t = t / np.linalg.norm(t)
            e1 = np.cross(t, [1.0, 0, 0]) if abs(t[0]) < 0.9 else np.cross(t, [0, 1.0, 0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(t, e1)
            ang = np.linspace(0, 2 * np.pi, directions, endpoint=False)
            dirs = np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2            # (D,3)
            rel = v - joints[j]
            dist = np.linalg.norm(rel, axis=1)
            cosine = (rel @ dirs.T) / np.maximum(dist[:, None], 1e-9)               # (V,D)
            inside = np.where(cosine > np.cos(np.radians(25)), dist[:, None], np.inf)
            nearest = inside.min(0)
            radii[j] = nearest[np.isfinite(nearest)].max()
        # a fingertip is a surface point: from behind the nail it lies a finger's thickness deep
        for tip in FINGER_TIPS:
            radii[tip] = 2.0 * radii[tip - 1]
        return radii

    @staticmethod
    def joint_parts():
        """(21,16) bool: the parts (joint frames) whose surface counts as showing joint j:
        the segments the joint connects (the palm for wrist, CMC and MCPs)."""
        adjacent = np.zeros((21, 16), bool)
        for j in range(21):
            if j in FINGER_TIPS:
                adjacent[j, NON_TIP_JOINTS.index(j - 1)] = True
                continue
            adjacent[j, NON_TIP_JOINTS.index(j)] = True
            parent = 0 if j in (1, 5, 9, 13, 17) else j - 1
            if j != 0:
                adjacent[j, NON_TIP_JOINTS.index(parent)] = True
        return adjacent

    # ------------------------------------------------------------ posing
    def pose(self, pose, beta, handedness_left=None):
        """Skin a batch of hands.

        pose: (N,16,3) relative axis-angle (or any format HandModel.joint_frames reads);
        beta: (N,B); handedness_left: (N,) bool, mirror those hands across x (left hands).
        Returns vertices (N,V,3) float32, normals (N,V,3) float32 (unit) and joints
        (N,21,3) float64, metres in the model frame.
        """
        frames = self.model.joint_frames(pose)                                 # (N,16,3,3)
        beta = np.asarray(beta, dtype=np.float64)
        n = len(frames)
        x_rest = self.model.rest_joints(beta)                                  # (N,21,3)
        joints = forward_kinematics(frames_to_bone_rotations(frames), x_rest)  # (N,21,3)
        v_rest = (self.v_template.astype(np.float32)
                  + (beta.astype(np.float32) @ self.shapedirs.T).reshape(n, -1, 3))
        if self.posedirs is not None:
            rel = frames_to_relative(frames)[..., POSE16_TO_MANO[1:], :, :]
            feat = (rel - np.eye(3)).reshape(n, -1)
            v_rest = v_rest + np.einsum("np,vcp->nvc", feat, self.posedirs).astype(np.float32)
        origin_rest = x_rest[:, NON_TIP_JOINTS]
        origin = joints[:, NON_TIP_JOINTS]
        trans = origin - (frames @ origin_rest[..., None])[..., 0]
        affine = np.concatenate([frames, trans[..., None]], axis=-1).astype(np.float32)   # (N,16,3,4)
        blended = (self.weights @ affine.reshape(n, 16, 12)).reshape(n, -1, 3, 4)      # (N,V,3,4)
        rot = blended[..., :3]
        vertices = (rot[..., 0] * v_rest[..., :1] + rot[..., 1] * v_rest[..., 1:2]
                    + rot[..., 2] * v_rest[..., 2:3] + blended[..., 3])
        rn = self.rest_normals.astype(np.float32)
        normals = rot[..., 0] * rn[:, :1] + rot[..., 1] * rn[:, 1:2] + rot[..., 2] * rn[:, 2:3]
        normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-9)
        if handedness_left is not None and np.any(handedness_left):
            flip = np.where(np.asarray(handedness_left)[:, None, None], -1.0, 1.0) * np.array([1.0, 0, 0])
            flip = flip + np.array([0.0, 1.0, 1.0])
            vertices = vertices * flip.astype(np.float32)
            normals = normals * flip.astype(np.float32)
            joints = joints * flip
        return vertices, normals, joints


def _smooth(edge0, edge1, x):
    """GLSL smoothstep, also for edge0 > edge1 (then falling)."""
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3 - 2 * t)
