"""Render the demo clip: the bundled hand model moving through gestures, with ground truth.

    python scripts/render_demo_clip.py [--out data/demo/hand_clip] [--frames 90]

Writes OUT.mp4 (640x480, 30 fps) and OUT.npz with, per frame, the 21 joints in camera
metres (`xyz`, (N,21,3)), their pixels (`uv`, (N,21,2)), the relative pose (`pose`, (N,16,3)),
`beta` (10,), `K` (3,3) and `handedness`. A right hand, palm to the camera, fingers up,
opening and closing (flat, fist, pointing, spread) while it drifts and turns; the background
is a smooth procedural texture. `launch/demo.yaml` replays it; end-to-end tests compare the
graph's output with the npz. Needs moderngl with EGL (handmocap/perception/render.py).
"""
import argparse
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.camera_info import default_K
from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import named_pose
from handmocap.perception.render import MeshRenderer
from handmocap.perception.rotations import axis_angle_to_quat, quat_slerp, quat_to_axis_angle

W, H, FPS = 640, 480, 30
GESTURES = ("flat", "fist", "pointing", "spread", "flat")


def gesture_poses(model, n):
    """(n,16,3) relative poses slerped through GESTURES, with a slowly turning wrist."""
    keys = axis_angle_to_quat(np.stack([named_pose(g, model) for g in GESTURES]))   # (G,16,4)
    t = np.linspace(0, len(GESTURES) - 1, n)
    i = np.minimum(t.astype(int), len(GESTURES) - 2)
    s = (t - i)[:, None]
    s = 0.5 - 0.5 * np.cos(np.pi * s)   # ease in and out of each gesture
    quats = quat_slerp(keys[i], keys[i + 1], np.broadcast_to(s, (n, 16)))
    pose = quat_to_axis_angle(quats)
    phase = np.linspace(0, 2 * np.pi, n)
    pose[:, 0] = np.stack([0.25 * np.sin(phase), 0.5 * np.sin(0.5 * phase), 0.15 * np.cos(phase)], 1)
    return pose


def background(rng):
    """A smooth, photo-like procedural texture (H,W,3) uint8."""
    noise = rng.random((H // 32, W // 32, 1)).astype(np.float32) * np.ones(3, np.float32)
    img = cv2.resize(noise, (W, H), interpolation=cv2.INTER_CUBIC)
    img = cv2.GaussianBlur(img, (0, 0), 20)
    grad = np.linspace(0.7, 1.1, H, dtype=np.float32)[:, None, None]
    tint = np.array([0.55, 0.6, 0.5], np.float32)
    return np.clip(255 * (0.25 + 0.6 * img * tint) * grad, 0, 255).astype(np.uint8)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "data/demo/hand_clip")
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    model = HandModel.load()
    beta = np.zeros(model.num_betas)
    K = default_K(W, H)
    poses = gesture_poses(model, args.frames)
    verts, joints = model.forward(poses, np.tile(beta, (args.frames, 1)))
    phase = np.linspace(0, 2 * np.pi, args.frames)
    # hand centre 0.45 m away, drifting a few centimetres; the model's wrist is its origin
    offset = np.stack([0.04 * np.sin(phase), 0.11 + 0.015 * np.cos(phase), 0.42 + 0.04 * np.sin(0.5 * phase)], 1)
    verts = verts + offset[:, None]
    xyz = joints + offset[:, None]
    uv = (xyz @ K.T)[..., :2] / xyz[..., 2:]
    renderer = MeshRenderer(W, H)
    bg = background(rng)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(args.out.with_suffix(".mp4")), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (W, H))
    for f in range(args.frames):
        rgb, depth = renderer.render([(verts[f], model.faces)], K, background=(0.0, 0.0, 0.0))
        mask = cv2.GaussianBlur((depth > 0).astype(np.float32), (3, 3), 0)[..., None]
        frame = (mask * cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) + (1 - mask) * bg).astype(np.uint8)
        writer.write(frame)
    writer.release()
    np.savez_compressed(args.out.with_suffix(".npz"), xyz=xyz.astype(np.float32), uv=uv.astype(np.float32),
                        pose=poses.astype(np.float32), beta=beta.astype(np.float32), K=K, handedness="right",
                        fps=FPS)
    print(f"wrote {args.out.with_suffix('.mp4')} and .npz ({args.frames} frames, {W}x{H})")


if __name__ == "__main__":
    main()
