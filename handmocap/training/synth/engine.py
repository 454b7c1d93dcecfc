"""SynthEngine: batches of labelled synthetic hand images.

>>> engine = SynthEngine(SynthConfig(mode="crop", size=128))
>>> batch = engine.batch(np.random.default_rng(0))      # dict of arrays, one row per image

One batch = one atlas pass (64 crops of 128 px, or 16 frames of 256 px): sample poses,
shapes, handedness, viewpoints and appearance; skin all hands at once; draw them and the
occluders into the atlas; read back colour, depth and surface ids; label; composite
over backgrounds; apply camera effects. Every random choice comes from the generator
passed in, so a seed reproduces a batch exactly.

Labels (n rows; float32 unless said):
  image (n,S,S,3) uint8 RGB           uv (n,21,2) px             xyz (n,21,3) camera m
  xyz_rel (n,21,3) root joint 9, |0-9| = 1                       K (n,3,3) of the image
  visible (n,21) bool (in image, not hidden by the hand itself or anything else)
  in_image (n,21) bool                handedness (n,) int8 0 right, 1 left
  box (n,4) x0,y0,x1,y1 px of the hand (and fingers, no forearm) vertices, unclipped
  pose (n,16,3) axis-angle, beta (n,10), translation (n,3): HandModel.forward(pose,
      beta, handedness) joints + translation = xyz (pose[0] is the camera-frame wrist
      rotation of the right hand that is mirrored into a left one)
  K_full (n,3,3), crop_box (n,4) x0,y0,side,side: the virtual full frame (crop mode)
  other_present (n,) bool, other_uv (n,21,2), other_visible (n,21) bool, other_box
      (n,4), other_handedness (n,) int8: a second hand in the image, if any
  occluders (n,) int8 objects in front of the hand; real_background (n,) bool
"""
from dataclasses import dataclass

import numpy as np

from handmocap.perception.hand_model import HandModel
from handmocap.perception.rotations import matrix_to_axis_angle, mirror_matrix, quat_to_matrix
from . import appearance, augment, objects, scene
from .atlas import ID_HAND, ID_OBJECT, ID_OTHER_HAND, AtlasRenderer
from .backgrounds import BackgroundSource, load_real_backgrounds
from .mesh import SynthHand
from .poses import PoseSampler

HANDEDNESS = ("right", "left")


@dataclass
class SynthConfig:
    """mode "crop": detector crops (hand box x crop_scale); "frame": whole frames."""
    mode: str = "crop"
    size: int = 128
    crop_scale: float = 1.3
    left_fraction: float = 0.5
    second_hand: float = 0.2           # probability of a second hand in the image
    touching: float = 0.0              # share of second hands placed palm to palm with the first
    pitched: float = 0.0               # share of first hands foreshortened (scene.sample_rotations)
    occluder: float = 0.35             # probability of 1-2 objects in front of the hand
    backgrounds: str = "auto"          # auto (real when cached / available), procedural
    real_fraction: float = 0.85        # share of real backgrounds when there are any
    augment: bool = True
    beta_sigma: float = 1.0


class SynthEngine:
    def __init__(self, config=None, model=None, seed=0, log=print):
        self.config = config or SynthConfig()
        if self.config.mode not in ("crop", "frame"):
            raise ValueError(f"mode must be 'crop' or 'frame', got {self.config.mode!r}")
        self.model = model or HandModel.load()
        self.hand = SynthHand(self.model)
        self.renderer = AtlasRenderer(self.hand, tile=self.config.size)
        self.capacity = self.renderer.capacity
        self.poses = PoseSampler(self.model)
        self.radius = self.hand.joint_radii() + 0.004
        self.adjacent = self.hand.joint_parts()
        self.ref_bone = float(self.model.ref_bone_length())
        real = None if self.config.backgrounds == "procedural" else load_real_backgrounds(log=log)
        self.backgrounds = BackgroundSource(np.random.default_rng(seed), real, self.config.real_fraction)
        self.noise = augment.SensorNoise(np.random.default_rng(seed + 1))

    # ------------------------------------------------------------------ sampling
    def _occluders(self, rng, joints_cam, n):
        """Objects between the camera and random joints of the labelled hands."""
        tris, draws, count = [], [], np.zeros(n, np.int8)
        first = 0
        has = rng.random(n) < self.config.occluder
        for i in np.flatnonzero(has):
            for _ in range(1 if rng.random() < 0.7 else 2):
                kind = objects.KINDS[rng.integers(len(objects.KINDS))]
                if kind == "sphere":
                    scale = np.full(3, rng.uniform(0.012, 0.04))
                elif kind == "box":
                    scale = rng.uniform(0.008, 0.05, 3)
                else:
                    r = rng.uniform(0.005, 0.03)
                    scale = np.array([r, r, rng.uniform(0.03, 0.12)])
                target = joints_cam[i, rng.integers(21)]
                ray = target / np.linalg.norm(target)
                centre = target - ray * (scale.max() + rng.uniform(0.01, 0.06))
                centre[:2] += rng.normal(0, 0.02, 2)
                if centre[2] - scale.max() < 0.05:
                    continue
                q = rng.normal(size=4)
                R = quat_to_matrix(q)
                t = objects.place(kind, scale, R, centre)
                tris.append(t)
                draws.append((i, first, len(t)))
                first += len(t)
                count[i] += 1
        tri = np.concatenate(tris) if tris else np.zeros((0, 9), np.float32)
        return tri, draws, count

    def batch(self, rng, n=None):
        """One atlas pass of n (<= capacity) labelled images; see the module doc."""
        cfg, T = self.config, self.config.size
        n = self.capacity if n is None else n
        if not 0 < n <= self.capacity:
            raise ValueError(f"n must be in 1..{self.capacity}")
        # -- hands: pose, shape, side; the second hand belongs to the same person
        pose1 = self.poses.sample(n, rng)
        beta1 = np.clip(rng.normal(0, cfg.beta_sigma, (n, self.model.num_betas)), -3, 3)
        left1 = rng.random(n) < cfg.left_fraction
        has2 = rng.random(n) < cfg.second_hand
        m = int(has2.sum())
        pose2 = self.poses.sample(m, rng)
        left2 = np.where(rng.random(m) < 0.9, ~left1[has2], left1[has2])
        verts, normals, joints = self.hand.pose(np.concatenate([pose1, pose2]), np.concatenate([beta1, beta1[has2]]),
                                                np.concatenate([left1, left2]))
        # -- primary hands: camera and crop
        R1, c1, p1, K_full = scene.place_hands(rng, joints[:n], cfg.mode, T, pitched_share=cfg.pitched)
        def to_cam(x, R, c, p):     # (n,P,3) model frame -> camera frame, batched matmul
            return ((x - c[:, None].astype(x.dtype)) @ np.swapaxes(R, 1, 2).astype(x.dtype)
                    + p[:, None].astype(x.dtype))
        v1 = to_cam(verts[:n], R1, c1, p1)
        hand_mask = self.hand.hand_vertex
        if cfg.mode == "crop":
            K, crop_box = scene.crop_intrinsics(rng, K_full, scene.project(K_full, v1[:, hand_mask]), T,
                                                cfg.crop_scale)
            native_scale = crop_box[:, 2] / T
        else:
            K, crop_box, native_scale = K_full.copy(), np.tile([0.0, 0.0, T, T], (n, 1)), np.ones(n)
        cam_verts = np.empty_like(verts)
        cam_normals = np.empty_like(normals)
        cam_verts[:n] = v1
        cam_normals[:n] = normals[:n] @ np.swapaxes(R1, 1, 2).astype(np.float32)
        xyz1 = to_cam(joints[:n], R1, c1, p1)
        # -- second hands next to the first (or, `touching`, palm to palm with it)
        R2 = scene.sample_rotations(rng, m)
        c2 = 0.5 * (joints[n:].min(1) + joints[n:].max(1))
        ang = rng.uniform(0, 2 * np.pi, m)
        dist = rng.uniform(0.09, 0.2, m)
        p2 = p1[has2] + np.stack([np.cos(ang) * dist, np.sin(ang) * dist, rng.normal(0, 0.06, m)], 1)
        p2[:, 2] = np.maximum(p2[:, 2], 0.15)
        # drawn only when asked, so shards made without --touching keep their seeds' images
        touch = rng.random(m) < cfg.touching if cfg.touching > 0 else np.zeros(m, bool)
        if touch.any():
            R2[touch], c2[touch], p2[touch] = scene.touching_placement(
                rng, R1[has2][touch], c1[has2][touch], p1[has2][touch])
        cam_verts[n:] = to_cam(verts[n:], R2, c2, p2)
        cam_normals[n:] = normals[n:] @ np.swapaxes(R2, 1, 2).astype(np.float32)
        xyz2 = to_cam(joints[n:], R2, c2, p2)
        # -- occluders, backgrounds, appearance
        obj_tri, obj_draws, occ_count = self._occluders(rng, xyz1, n)
        bg, real_bg = self.backgrounds.sample(rng, n, T)
        bg_linear = appearance.to_linear(bg[:, ::4, ::4].reshape(n, -1, 3).mean(1, dtype=np.float32) / 255.0)
        lights = appearance.light_blocks(rng, n, bg_linear)
        base, palm, nail, dark = appearance.sample_skin(rng, n)
        owner = np.concatenate([np.arange(n), np.flatnonzero(has2)])
        mats = appearance.material_blocks(rng, base[owner], palm[owner], nail[owner], dark[owner],
                                          np.r_[np.full(n, ID_HAND), np.full(m, ID_OTHER_HAND)])
        mats[n:, 3] = mats[owner[n:], 3]                   # same sleeve on both arms
        obj_mats = appearance.object_blocks(rng, len(obj_draws), ID_OBJECT)
        left = np.concatenate([left1, left2])
        hand_draws = [(int(owner[h]), h, mats[h], bool(left[h])) for h in range(n + m)]
        object_draws = [(t, f, c, obj_mats[k]) for k, (t, f, c) in enumerate(obj_draws)]
        rgb, alpha, depth, ids, parts = self.renderer.render(
            K, cam_verts, cam_normals, hand_draws, obj_tri, object_draws, lights)
        # -- labels
        uv1 = scene.project(K, xyz1)
        hand_scale = self.model.ref_bone_length(beta1) / self.ref_bone
        visible, in_image = scene.joint_visibility(uv1, xyz1, depth, ids, parts, ID_HAND,
                                                   self.radius[None] * hand_scale[:, None], self.adjacent, T)
        other_uv = np.zeros((n, 21, 2))
        other_visible = np.zeros((n, 21), bool)
        other_box = np.zeros((n, 4))
        other_hand = np.full(n, -1, np.int8)
        if m:
            Kh = K[has2]
            other_uv[has2] = scene.project(Kh, xyz2)
            scale2 = hand_scale[has2]
            other_visible[has2] = scene.joint_visibility(
                other_uv[has2], xyz2, depth[has2], ids[has2], parts[has2], ID_OTHER_HAND,
                self.radius[None] * scale2[:, None], self.adjacent, T)[0]
            other_box[has2] = scene.boxes(scene.project(Kh, cam_verts[n:, hand_mask]))
            other_hand[has2] = left2.astype(np.int8)
        pose_label = pose1.copy()
        wrist = np.where(left1[:, None, None], mirror_matrix(R1), R1)
        pose_label[:, 0] = matrix_to_axis_angle(wrist)
        rest_wrist = self.model.rest_joints(beta1)[:, 0] * np.where(left1[:, None], [-1.0, 1, 1], 1.0)
        translation = xyz1[:, 0] - np.einsum("nij,nj->ni", wrist, rest_wrist)
        # -- image
        image = self._finish(rng, rgb, alpha, depth, bg, native_scale)
        f32 = lambda a: np.asarray(a, np.float32)
        return {
            "image": image, "uv": f32(uv1), "xyz": f32(xyz1), "xyz_rel": f32(scene.normalized_root_relative(xyz1)),
            "K": f32(K), "visible": visible, "in_image": in_image, "handedness": left1.astype(np.int8),
            "box": f32(scene.boxes(scene.project(K, v1[:, hand_mask]))),
            "pose": f32(pose_label), "beta": f32(beta1), "translation": f32(translation),
            "K_full": f32(K_full), "crop_box": f32(crop_box),
            "other_present": has2, "other_uv": f32(other_uv), "other_visible": other_visible,
            "other_box": f32(other_box), "other_handedness": other_hand,
            "occluders": occ_count, "real_background": real_bg,
        }

    def _finish(self, rng, rgb, alpha, depth, bg, native_scale):
        """Composite the rendered layers over the backgrounds and apply camera effects."""
        n = len(rgb)
        if not self.config.augment:
            return augment.composite(rgb, alpha, bg)
        augment.ambient_occlusion(rgb, depth, alpha, rng.uniform(0.2, 0.6, n))
        augment.contact_shadow(bg, alpha, rng, rng.random(n) < 0.3)
        img = augment.composite(rgb, alpha, bg)
        sensor_scale = augment.optics(img, rng, native_scale)
        augment.colour_jitter(img, rng)
        img = self.noise(img, rng, sensor_scale)
        return augment.jpeg(img, rng)

    def release(self):
        self.renderer.release()
