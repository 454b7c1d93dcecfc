"""HandModel: a MANO-style right-hand model driven by 21 joints' rotations and 10 shape coefficients.

Two sources, one interface:
* the bundled open model, models/hand_model.npz (MakeHuman/MPFB2, CC0; built by
  scripts/build_hand_model.py; frame: metres, wrist at the origin, fingers along -y,
  thumb side +x, palm facing -z; see models/README.md);
* a MANO_RIGHT.pkl the user owns (MANO's own frame and units, metres), read without chumpy.

Pose conventions are those of handmocap.perception.kinematics: a relative MANO-style pose (16, 3)
axis-angle over skeleton.NON_TIP_JOINTS (project order, not MANO's: use
kinematics.pose16_from_mano), or 21 global bone quaternions (21, 4) (w, x, y, z) where
q_0 rotates the wrist (palm and forearm, the whole hand) and q_j, j >= 1, rotates the
rest bone parent(j) -> j. Pose zero is the template (a flat, slightly relaxed hand), not
MANO's hands_mean; `mean_pose` holds that where the file has one.

forward() is linear blend skinning (Eq. 6-7 of the paper), in the model frame:
    v_shaped = T + S beta                          (V,3)   shape blend shapes
    x_rest   = J + S_J beta                        (21,3)  rest joints, linear in beta
    v_rest   = v_shaped + P (R_rel - I)            (V,3)   pose blend shapes (MANO only)
    x        = FK(q, x_rest)                       (21,3)  all 21 joints, tips included
    v        = sum_k w_vk (G_k (v_rest - x_rest_k) + x_k)   over the 16 joint frames k
"""
import pickle
from pathlib import Path

import numpy as np

from handmocap.perception.kinematics import (
    POSE16_FROM_MANO, POSE16_TO_MANO, as_matrices, bone_rotations_to_frames, forward_kinematics,
    frames_to_bone_rotations, frames_to_relative, relative_to_frames,
)
from handmocap.perception.rotations import mirror_points
from handmocap.perception.skeleton import FROM_MANO_ORDER, HAND_LENGTH_JOINTS, NON_TIP_JOINTS, NUM_JOINTS, REF_BONE

MODELS_DIR = Path(__file__).resolve().parents[2] / "models"
BUNDLED_MODEL = MODELS_DIR / "hand_model.npz"

# MANO vertices used as fingertips, in order thumb, index, middle, ring, little
MANO_TIP_VERTICES = (745, 317, 444, 556, 673)
# MANO's kinematic tree (parents in MANO's joint order), checked on load
MANO_PARENTS = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14)


class HandModel:
    """A skinned right hand. Arrays (V vertices, B shape coefficients):

    v_template (V,3), shapedirs (V,3,B), weights (V,16) over the joint frames of
    NON_TIP_JOINTS, faces (F,3) int (counter-clockwise seen from outside),
    j_template (21,3), j_shapedirs (21,3,B), posedirs (V,3,135) or None,
    tip_vertex_ids (5,), beta_names (B,), mean_pose (16,3) axis-angle.
    """

    def __init__(self, v_template, shapedirs, weights, faces, j_template, j_shapedirs,
                 tip_vertex_ids, posedirs=None, beta_names=None, mean_pose=None, name="hand"):
        self.v_template = np.asarray(v_template, dtype=np.float64)
        self.shapedirs = np.asarray(shapedirs, dtype=np.float64)
        self.weights = np.asarray(weights, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.j_template = np.asarray(j_template, dtype=np.float64)
        self.j_shapedirs = np.asarray(j_shapedirs, dtype=np.float64)
        self.tip_vertex_ids = np.asarray(tip_vertex_ids, dtype=np.int64)
        self.posedirs = None if posedirs is None else np.asarray(posedirs, dtype=np.float64)
        self.num_betas = self.shapedirs.shape[-1]
        self.beta_names = tuple(beta_names) if beta_names is not None else tuple(
            f"beta{i}" for i in range(self.num_betas))
        self.mean_pose = np.zeros((16, 3)) if mean_pose is None else np.asarray(mean_pose, dtype=np.float64)
        self.name = name
        if self.weights.shape != (len(self.v_template), 16):
            raise ValueError(f"weights must be (V,16), got {self.weights.shape}")

    # ---------------------------------------------------------------- loading
    @classmethod
    def load(cls, path=None):
        """The bundled open model (path None), a model .npz, or a MANO_RIGHT.pkl."""
        path = BUNDLED_MODEL if path is None else Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"hand model {path} not found")
        try:
            if path.suffix == ".pkl":
                return cls.from_mano(path)
            data = np.load(path, allow_pickle=False)
            return cls(
                v_template=data["v_template"], shapedirs=data["shapedirs"], weights=data["weights"],
                faces=data["faces"], j_template=data["j_template"], j_shapedirs=data["j_shapedirs"],
                tip_vertex_ids=data["tip_vertex_ids"],
                posedirs=data["posedirs"] if "posedirs" in data else None,
                beta_names=[str(s) for s in data["beta_names"]] if "beta_names" in data else None,
                name=path.stem,
            )
        except Exception as e:   # a cut or foreign file: zipfile, pickle, numpy and key errors alike
            # numpy's own words would suggest allow_pickle, which runs code from the file: not said
            cause = "not an .npz of arrays" if "pickle" in str(e) else f"{type(e).__name__}: {str(e)[:200]}"
            raise ValueError(f"hand model {path} is not a readable hand model file ({cause}); the bundled one "
                             f"is models/hand_model.npz, made by scripts/build_hand_model.py") from None

    @classmethod
    def from_mano(cls, path):
        """Read a MANO_RIGHT.pkl (chumpy/scipy objects inside) without chumpy or scipy."""
        with open(path, "rb") as fh:
            raw = _MANOUnpickler(fh, encoding="latin1").load()
        arr = {k: _to_array(v) for k, v in raw.items()}
        parents = tuple(int(p) if p < 2 ** 31 - 1 else -1 for p in arr["kintree_table"][0])
        parents = (-1,) + parents[1:]
        if parents != MANO_PARENTS:
            raise ValueError(f"{path}: unexpected MANO kinematic tree {parents}")
        v_template = arr["v_template"]
        shapedirs = arr["shapedirs"]
        regressor = arr["J_regressor"]                          # (16, V), MANO joint order
        tips = list(MANO_TIP_VERTICES)
        j_mano = np.concatenate([regressor @ v_template, v_template[tips]])          # (21,3)
        js_mano = np.concatenate([np.einsum("jv,vcb->jcb", regressor, shapedirs), shapedirs[tips]])
        posedirs = arr.get("posedirs")
        mean_pose = None
        if "hands_mean" in arr:                                 # 15 finger joints, MANO order
            mean_mano = np.concatenate([np.zeros(3), arr["hands_mean"].ravel()]).reshape(16, 3)
            mean_pose = mean_mano[POSE16_FROM_MANO]
        return cls(
            v_template=v_template, shapedirs=shapedirs, faces=arr["f"].astype(np.int64),
            weights=arr["weights"][:, POSE16_FROM_MANO],        # columns to project frame order
            j_template=j_mano[FROM_MANO_ORDER], j_shapedirs=js_mano[FROM_MANO_ORDER],
            tip_vertex_ids=np.array(tips), posedirs=posedirs,
            mean_pose=mean_pose, name=Path(path).stem,
        )

    def save(self, path):
        """Write this model in the bundled .npz format."""
        extra = {} if self.posedirs is None else {"posedirs": self.posedirs.astype(np.float32)}
        np.savez_compressed(
            path, v_template=self.v_template.astype(np.float32), faces=self.faces.astype(np.int32),
            weights=self.weights.astype(np.float32), shapedirs=self.shapedirs.astype(np.float32),
            j_template=self.j_template.astype(np.float32), j_shapedirs=self.j_shapedirs.astype(np.float32),
            tip_vertex_ids=self.tip_vertex_ids.astype(np.int32), beta_names=np.array(self.beta_names), **extra)

    # ---------------------------------------------------------------- shape
    def _beta(self, beta):
        beta = np.zeros(self.num_betas) if beta is None else np.asarray(beta, dtype=np.float64)
        if beta.shape[-1] > self.num_betas:
            raise ValueError(f"model has {self.num_betas} shape coefficients, got {beta.shape[-1]}")
        if beta.shape[-1] < self.num_betas:   # fewer coefficients: the rest are zero
            beta = np.concatenate([beta, np.zeros(beta.shape[:-1] + (self.num_betas - beta.shape[-1],))], -1)
        return beta

    def rest_joints(self, beta=None):
        """(..., 21, 3) rest-pose joints in metres for beta (..., B) (None: the average hand)."""
        return self.j_template + np.einsum("...b,jcb->...jc", self._beta(beta), self.j_shapedirs)

    def shaped_vertices(self, beta=None):
        """(..., V, 3) rest-pose vertices in metres for beta (..., B)."""
        return self.v_template + np.einsum("...b,vcb->...vc", self._beta(beta), self.shapedirs)

    def ref_bone_length(self, beta=None):
        """(...,) length in metres of the reference bone 0 -> 9 at rest."""
        j = self.rest_joints(beta)
        return np.linalg.norm(j[..., REF_BONE[1], :] - j[..., REF_BONE[0], :], axis=-1)

    def hand_length(self, beta=None):
        """(...,) rest length in metres from the wrist joint to the middle fingertip (a ruler's
        hand length: wrist crease to the tip of the middle finger) for beta (..., B)."""
        j = self.rest_joints(beta)
        return np.linalg.norm(j[..., HAND_LENGTH_JOINTS[1], :] - j[..., HAND_LENGTH_JOINTS[0], :], axis=-1)

    def sized(self, beta, hand_length):
        """beta (B,) with its `hand_size` coefficient set so that the rest hand is hand_length
        metres from wrist to middle fingertip (HandModel.hand_length); the others kept.

        Exact: the rest joints are linear in beta, so with s the size coefficient the wrist ->
        tip vector is c + d s and |c + d s| = hand_length is a quadratic in s; of its roots
        the one of the larger hand (the other flips the hand through itself)."""
        beta = self._beta(beta).astype(np.float64).copy()
        k = self.beta_names.index("hand_size")
        beta[k] = 0.0
        j0 = self.rest_joints(beta)
        wrist, tip = HAND_LENGTH_JOINTS
        c = j0[tip] - j0[wrist]                                                 # (3,)
        d = self.j_shapedirs[tip, :, k] - self.j_shapedirs[wrist, :, k]         # (3,)
        a, b, cc = d @ d, 2.0 * (c @ d), c @ c - float(hand_length) ** 2
        beta[k] = (-b + np.sqrt(max(b * b - 4.0 * a * cc, 0.0))) / (2.0 * a)
        return beta

    # ---------------------------------------------------------------- posing
    @staticmethod
    def joint_frames(pose):
        """(..., 16, 3, 3) global joint frames for any accepted pose format (see forward)."""
        pose = np.asarray(pose, dtype=np.float64)
        is_matrix = pose.ndim >= 3 and pose.shape[-2:] == (3, 3)
        count = pose.shape[-3] if is_matrix else pose.shape[-2]
        if count == 16:                           # relative, MANO-style
            return relative_to_frames(as_matrices(pose))
        if count == NUM_JOINTS:                   # global bone rotations, IKNet-style
            return bone_rotations_to_frames(as_matrices(pose))
        raise ValueError(f"pose must be (...,16,3|4|3x3) relative or (...,21,4|3x3) global, got {pose.shape}")

    def forward(self, pose=None, beta=None, handedness="right"):
        """Posed vertices and joints.

        pose: relative (16,3) axis-angle [or (16,4) quaternions, (16,3,3) matrices] over
              NON_TIP_JOINTS, or global bone rotations (21,4) quaternions (w,x,y,z) [or
              (21,3,3)]; optionally with leading batch dims (N, ...). None: rest pose.
        beta: (B,) or (N,B) shape coefficients; None: the average hand.
        handedness: "left" mirrors the result across x (x -> -x): the pose and shape are
              those of the mirrored (right) hand; draw it with faces_for("left").
        Returns vertices (..., V, 3) and joints (..., 21, 3), metres, in the model frame.
        """
        if pose is None:
            pose = np.zeros((16, 3))
        frames = self.joint_frames(pose)                                    # (...,16,3,3)
        beta = self._beta(beta)
        x_rest = self.rest_joints(beta)                                     # (...,21,3)
        v_rest = self.shaped_vertices(beta)                                 # (...,V,3)
        if self.posedirs is not None:
            rel = frames_to_relative(frames)[..., POSE16_TO_MANO[1:], :, :]   # MANO order, no wrist
            feat = (rel - np.eye(3)).reshape(rel.shape[:-3] + (-1,))        # (...,135)
            v_rest = v_rest + np.einsum("...p,vcp->...vc", feat, self.posedirs)
        joints = forward_kinematics(frames_to_bone_rotations(frames), x_rest)   # (...,21,3)
        vertices = self.skin(v_rest, frames, x_rest, joints)
        if handedness == "left":
            return mirror_points(vertices), mirror_points(joints)
        if handedness != "right":
            raise ValueError(f"handedness must be 'left' or 'right', got {handedness!r}")
        return vertices, joints

    def skin(self, v_rest, frames, x_rest, joints):
        """Linear blend skinning.

        v_rest (..., V, 3) rest vertices; frames (..., 16, 3, 3) joint rotations G_k;
        x_rest, joints (..., 21, 3) rest and posed joints. Returns (..., V, 3).
        Each frame k is the rigid map v -> G_k (v - x_rest_k) + x_k; the per-vertex
        blend of the 16 maps is one (V,16) @ (16,12) product.
        """
        origin_rest = x_rest[..., NON_TIP_JOINTS, :]
        origin = joints[..., NON_TIP_JOINTS, :]
        trans = origin - (frames @ origin_rest[..., None])[..., 0]          # (...,16,3)
        affine = np.concatenate([frames, trans[..., None]], axis=-1)        # (...,16,3,4)
        blended = (self.weights @ affine.reshape(affine.shape[:-3] + (16, 12))).reshape(
            affine.shape[:-3] + (-1, 3, 4))                                 # (...,V,3,4)
        return np.einsum("...vab,...vb->...va", blended[..., :3], v_rest) + blended[..., 3]

    def faces_for(self, handedness="right"):
        """(F,3) faces; mirrored (left) meshes need the reversed winding to face outwards."""
        return self.faces if handedness == "right" else self.faces[:, ::-1]


# ------------------------------------------------------------------ MANO pickle reading
class _PickledArrayStub:
    """Stands in for chumpy.Ch and scipy.sparse matrices while unpickling a MANO file.

    It records whatever state the pickle restores; _to_array() turns it into an ndarray.
    """
    kind = "chumpy"

    def __init__(self, *args, **kwargs):
        self.state = {}
        self.args = args

    def __setstate__(self, state):
        if isinstance(state, tuple) and len(state) == 2:      # (dict, slots) form
            state = {**(state[0] or {}), **(state[1] or {})}
        self.state = state if isinstance(state, dict) else {"x": state}


class _SparseStub(_PickledArrayStub):
    kind = "sparse"


class _MANOUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if module.split(".")[0] == "chumpy":
            return type(name, (_PickledArrayStub,), {})
        if module.startswith("scipy.sparse"):
            return type(name, (_SparseStub,), {"fmt": name[:3]})
        return super().find_class(module, name)


def _to_array(obj):
    """ndarray for a stub (chumpy: its 'x'; scipy.sparse: densified), else np.asarray."""
    if isinstance(obj, _SparseStub):
        s = obj.state
        shape = tuple(s.get("_shape", s.get("shape")))
        dense = np.zeros(shape)
        data = np.asarray(s["data"], dtype=np.float64)
        if obj.fmt in ("csc", "csr"):
            indptr, indices = np.asarray(s["indptr"]), np.asarray(s["indices"])
            outer = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
            rows, cols = (indices, outer) if obj.fmt == "csc" else (outer, indices)
        elif obj.fmt == "coo":
            rows, cols = np.asarray(s["row"]), np.asarray(s["col"])
        else:
            raise ValueError(f"unsupported sparse format {obj.fmt}")
        np.add.at(dense, (rows, cols), data)
        return dense
    if isinstance(obj, _PickledArrayStub):
        for key in ("x", "a", "_x"):
            if key in obj.state:
                return _to_array(obj.state[key])
        raise ValueError(f"cannot find the array in a pickled chumpy object: keys {sorted(obj.state)}")
    if isinstance(obj, (str, bytes)):
        return obj
    return np.asarray(obj)
