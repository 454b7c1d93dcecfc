"""The pose stage's 3D on training-side data: DetNet's joints, their x, y moved onto the 2D
(`xy_from_keypoints`), and the pipeline's posed joints (IKNet + limits clamp + FK).

    python research/pose_stage_vs_world.py [--synthetic runs/detnet_data/synth_val] [--clips]
                                          [--limits]

--synthetic DIR: held-out rendered crops (a `handsynth generate` folder DetNet did not train
    on; left hands mirrored for DetNet and back), DetNet's 3D with x, y moved by each weight
    onto the ones its 2D implies through the crop's K: mean mm and AUC 20-50 mm, root and
    scale aligned (as `handeval`).
--clips: the real clips of shared/data/video (webcam, dex_retargeting, tfjs_asl; DetNet's
    training clips, so only a relative check) through HandDetector, against MediaPipe's world
    landmarks (its own 3D, roughly camera-aligned, scaled to a 90 mm wrist -> middle MCP
    bone; the 60-degree default K): AUC 20-50 mm per clip of
    DetNet alone, of each xy weight, and of the pipeline with and without the limits clamp.
--limits: where IKNet's unclamped finger angles on those clips (every 3rd frame of five
    clips) leave the anatomical limits, per joint: the share outside and the 5/50/95th
    percentiles of flexion, abduction and twist in degrees.
The evaluation splits are never read.
"""
import argparse
import glob
from pathlib import Path

import numpy as np

from handmocap.perception import camera_info
from handmocap.perception.detector import HandDetector
from handmocap.perception.detnet_runner import DetNetRunner
from handmocap.runtime.frames import read_video
from handmocap.perception.hand_model import HandModel
from handmocap.perception.ik_solver import IKSolver
from handmocap.perception.joint_limits import FINGER_JOINTS, JointLimits
from handmocap.perception.kinematics import global_quats_to_relative
from handmocap.training.metrics import PCK_THRESHOLDS_MM, align_to_ground_truth, auc, joint_errors, pck
from handmocap.perception.pose import PoseEstimator, joints_for_iknet, solve_rotations
from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.shape import ShapeEstimator
from handmocap.perception.skeleton import normalize_joints
from handmocap.perception.translation import joints_through_keypoints

WEIGHTS = (0.0, 0.25, 0.4, 0.5, 0.6, 0.75, 1.0)


def error_mm(pred, xyz):
    """(N,21) mm between predictions root- and scale-aligned onto the truth (N,21,3) m, as `handeval`."""
    return 1000 * joint_errors(align_to_ground_truth(pred, xyz), xyz)


def summary(err):
    return f"{err.mean():.2f} mm / {auc(PCK_THRESHOLDS_MM, pck(err, PCK_THRESHOLDS_MM)):.3f}"


def synthetic(folder):
    detnet = DetNetRunner.load()
    for shard in sorted(Path(folder).glob("shard_*.npz")):
        d = np.load(shard)
        uv, xyz = [], []
        for i in range(0, len(d["image"]), 64):
            crops, left = d["image"][i:i + 64].copy(), d["handedness"][i:i + 64] == 1
            crops[left] = crops[left][:, :, ::-1]
            out = detnet(crops)
            out["uv"][left, :, 0] = crops.shape[2] - 1 - out["uv"][left, :, 0]
            out["xyz"][left, :, 0] *= -1
            uv.append(out["uv"]), xyz.append(out["xyz"])
        uv, P = np.concatenate(uv).astype(float), normalize_joints(np.concatenate(xyz).astype(float))
        K, truth = d["K"].astype(float), d["xyz"].astype(float)
        print(f"{shard} ({len(uv)} crops), mean mm / AUC 20-50 mm:")
        for w in WEIGHTS:
            print(f"  x, y weight {w:.2f}: {summary(error_mm(joints_through_keypoints(K, uv, P, w), truth))}")
        true_2d = joints_through_keypoints(K, d["uv"], P, 1.0)
        print(f"  the true 2D, DetNet's depths: {summary(error_mm(true_2d, truth))}")


def clip_paths(shared):
    return sorted(glob.glob(str(shared / "video" / "webcam" / "*.mp4"))) + \
        [str(shared / "video" / "dex_retargeting" / "human_hand_video.mp4"),
         str(shared / "video" / "tfjs_asl_hand" / "asl_hand.25fps.mp4")]


def nearest_world(mp, i, uv, max_px=40.0, ref_bone_m=0.09):
    """MediaPipe's world landmarks (21,3) of the hand nearest uv on frame i, scaled to a
    `ref_bone_m` wrist -> middle MCP bone (its own scale drifts with the view), or None."""
    best = None
    for k in range(mp["found"].shape[1]):
        if mp["found"][i, k]:
            d = np.linalg.norm(mp["uv"][i, k] - uv, axis=-1).mean()
            if d < max_px and (best is None or d < best[0]):
                best = (d, k)
    if best is None:
        return None
    world = mp["world"][i, best[1]].astype(float)
    return world * ref_bone_m / np.linalg.norm(world[0] - world[9])


def clips(shared):
    model = HandModel.load()
    solver = IKSolver.load(model=model)
    settings = {"pipeline": {}, "pipeline, no clamp": {"clamp_to_limits": False}}
    for path in clip_paths(shared):
        mp = np.load(path.replace(".mp4", ".mediapipe.npz"))
        fps = float(mp["fps"])
        detector, frames = HandDetector.load(), []
        for i, image in enumerate(read_video(path)):
            frames.append((i, detector.process(image)))
        K = camera_info.default_K(image.shape[1], image.shape[0])
        rows = {}
        for name, params in settings.items():
            shapes, poses = ShapeEstimator(model), PoseEstimator(solver, model, **params)
            rows[name] = []
            for i, hands in frames:
                poses.set_shapes(shapes.update(hands, i / fps))
                rows[name] += [(i, h, p["xyz"]) for h, p in zip(hands, poses.update(hands, K, i / fps))]
        line = [Path(path).name]
        for key in ("DetNet",) + tuple(f"w {w:.2f}" for w in WEIGHTS[1:]) + tuple(settings):
            pred, gt = [], []
            for i, hand, posed in rows["pipeline" if key not in settings else key]:
                world = nearest_world(mp, i, hand["uv"])
                if world is None:
                    continue
                gt.append(world)
                if key == "DetNet":
                    pred.append(hand["xyz_rel"])
                elif key.startswith("w "):
                    pred.append(joints_through_keypoints(K, hand["uv"], hand["xyz_rel"], float(key[2:])))
                else:
                    pred.append(posed)
            err = error_mm(np.array(pred, float), np.array(gt))
            line.append(f"{key} {auc(PCK_THRESHOLDS_MM, pck(err, PCK_THRESHOLDS_MM)):.3f}")
        print(" | ".join(line), flush=True)


def limits_table(shared):
    model = HandModel.load()
    solver, limits = IKSolver.load(model=model), JointLimits.for_model(model)
    angles = []
    for path in clip_paths(shared)[:4] + clip_paths(shared)[-2:-1]:
        detector = HandDetector.load()
        for i, image in enumerate(read_video(path)):
            if i % 3:
                continue
            K = camera_info.default_K(image.shape[1], image.shape[0])
            for hand in detector.process(image):
                q = solve_rotations(joints_for_iknet(hand, K), hand["handedness"], model.rest_joints(), solver)
                angles.append(limits.angles(global_quats_to_relative(q)))
    a, lim = np.degrees(np.array(angles)), np.degrees(limits.limits)
    print(f"{len(a)} hands; per joint and angle: [limits] share outside, 5/50/95th percentiles (deg)")
    for k, joint in enumerate(FINGER_JOINTS):
        cells = []
        for c, name in enumerate(("flexion", "abduction", "twist")):
            outside = np.mean((a[:, k, c] < lim[k, c, 0]) | (a[:, k, c] > lim[k, c, 1]))
            p = np.percentile(a[:, k, c], [5, 50, 95])
            cells.append(f"{name} [{lim[k, c, 0]:.0f},{lim[k, c, 1]:.0f}] {outside:4.0%} "
                         f"{p[0]:6.1f} {p[1]:6.1f} {p[2]:6.1f}")
        print(f"joint {joint:2d} | " + " | ".join(cells))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synthetic", metavar="DIR", help="held-out handsynth folder (e.g. runs/detnet_data/synth_val)")
    ap.add_argument("--clips", action="store_true")
    ap.add_argument("--limits", action="store_true")
    ap.add_argument("--shared", type=Path, default=SHARED_DATA)
    args = ap.parse_args()
    if args.synthetic:
        synthetic(args.synthetic)
    if (args.clips or args.limits) and not (args.shared / "video").is_dir():
        raise SystemExit(f"error: {args.shared / 'video'}: no shared data here")
    if args.clips:
        clips(args.shared)
    if args.limits:
        limits_table(args.shared)


if __name__ == "__main__":
    main()
