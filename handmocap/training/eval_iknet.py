"""Evaluate IKNet (the exported ONNX model, as shipped) beside the analytic IK baseline.

    python -m handmocap.training.eval_iknet [--model int8|float32|PATH] [--n 10000] [--pairs PAIRS.npz]

(default: the file IKSolver.load opens by default, models/iknet_int8.onnx)

Data, none of it seen in training:
* synthetic: n poses from PoseSampler with seed EVAL_SEED (training batches use
  generator [seed, iteration], validation VAL_SEED), rest pose at each sample's beta;
  clean input, and the same poses with emulated detector errors (corrupt_joints);
* real: the held-back MediaPipe world-landmark clips (pose_data.REAL_EVAL), rest pose fitted
  to each frame's bone ratios; these are not ground truth, so only the FK error against the
  input joints (how faithfully the rotations explain them) and the joint-limit share mean
  anything there.
Metrics: rotation error = angle between predicted and true global bone rotations, mean
over hands and the 21 bones (and over the 15 finger bones that carry a joint limit);
FK error = mean distance of the model posed by the rotations (at the sample's rest pose)
to the true clean joints, mm with the reference bone scaled to 95 mm; limits = share of the
15 finger joints within the anatomical limits (JointLimits of the average hand, 0.5 deg
tolerance). "clamped to limits" clips IKNet's finger angles into those limits
(ik_solver.clamp_to_limits, down each finger, keeping each bone's direction as far as
the limits allow), as the ik node does by default.

--pairs PAIRS.npz (scripts/detnet_noisy_pairs.py on a held-out shard, e.g. the synthetic
validation shard): the paper's Table 2 on a real detector's output. DetNet's 3D of
rendered crops against the rendered truth, alone and through IKNet + FK at the true rest
pose: mean joint error (mm, reference bone 95 mm) and 3D AUC over 20-50 mm.
"""
import argparse
import time

import numpy as np

from handmocap.perception.hand_model import HandModel
from handmocap.perception.ik_solver import IKSolver, analytic_ik, clamp_to_limits, model_path
from handmocap.perception.joint_limits import JointLimits
from handmocap.perception.kinematics import bone_rotations_to_frames, forward_kinematics, frames_to_bone_rotations
from handmocap.training.metrics import PCK_THRESHOLDS_MM, auc, pck
from handmocap.training.pose_data import REAL_EVAL, SHARED_DATA, PositionPairs, PoseSampler, corrupt_joints, load_real_sequences
from handmocap.perception.rotations import quat_angle_between, quat_to_matrix
from handmocap.perception.skeleton import normalize_joints

EVAL_SEED = 20_200_614
REF_MM = 95.0
FINGER_BONES = [2, 3, 4, 6, 7, 8, 10, 11, 12, 14, 15, 16, 18, 19, 20]   # q_j = frame of a limited joint


def fk_joints(quats, rest):
    """Normalized joints of the model posed by bone quaternions (rigid palm, as HandModel)."""
    bones = frames_to_bone_rotations(bone_rotations_to_frames(quat_to_matrix(quats)))
    return normalize_joints(forward_kinematics(bones, rest))


def solve_in_batches(solver, xyz, rest, batch=1000):
    """IKSolver.solve over (N,21,3) joints and rest poses, `batch` hands per call."""
    return np.concatenate([solver.solve(xyz[i:i + batch], rest[i:i + batch]) for i in range(0, len(xyz), batch)])


def metrics(quats, rest, target, limits, quats_true=None):
    out = {"fk_mm": np.linalg.norm(fk_joints(quats, rest) - target, axis=-1).mean() * REF_MM,
           "limits_pct": 100.0 * limits.within(quats).mean()}
    if quats_true is not None:
        angle = np.degrees(quat_angle_between(quats, quats_true))
        out["rot_deg"] = angle.mean()
        out["rot_finger_deg"] = angle[:, FINGER_BONES].mean()
    return out


def evaluate(solver, n=10000, data_root=SHARED_DATA, batch=1000):
    """{(dataset, method): metrics} and the noise put in (mm)."""
    model = HandModel.load()
    limits = JointLimits.for_model(model)
    rng = np.random.default_rng(EVAL_SEED)
    poses = PoseSampler(model).sample(n, rng)
    noisy = corrupt_joints(poses["xyz"], rng)
    def iknet(x, r):
        return solve_in_batches(solver, x, r, batch)

    methods = {"IKNet": iknet,
               "IKNet, clamped to limits": lambda x, r: clamp_to_limits(iknet(x, r), limits),
               "analytic (swing, no twist)": analytic_ik}
    results = {}
    for method, solve in methods.items():
        results["synthetic clean", method] = metrics(solve(poses["xyz"], poses["rest"]), poses["rest"],
                                                     poses["xyz"], limits, poses["quats"])
        results["synthetic noisy", method] = metrics(solve(noisy, poses["rest"]), poses["rest"],
                                                     poses["xyz"], limits, poses["quats"])
    noise_mm = np.linalg.norm(noisy - poses["xyz"], axis=-1).mean() * REF_MM
    sequences = load_real_sequences(REAL_EVAL, data_root)
    if sequences:
        real = PositionPairs.from_sequences(sequences, model)
        for method, solve in methods.items():
            results["real held-out", method] = metrics(solve(real.inputs, real.rest), real.rest, real.targets, limits)
        results["real held-out", "(frames)"] = len(real)
    return results, noise_mm


def evaluate_pairs(solver, path, batch=1000):
    """{method: (mean joint error mm, AUC 20-50 mm)} on a detector's output (PositionPairs.from_npz)."""
    model = HandModel.load()
    limits = JointLimits.for_model(model)
    pairs = PositionPairs.from_npz(path, model)
    x, rest, target = pairs.inputs, pairs.rest, pairs.targets
    quats = solve_in_batches(solver, x, rest, batch)
    joints = {"the detector's joints (DetNet alone)": x,
              "IKNet + FK": fk_joints(quats, rest),
              "IKNet, clamped to limits, + FK": fk_joints(clamp_to_limits(quats, limits), rest)}
    out = {}
    for method, xyz in joints.items():
        err_mm = np.linalg.norm(xyz - target, axis=-1) * REF_MM
        out[method] = (float(err_mm.mean()), auc(PCK_THRESHOLDS_MM, pck(err_mm, PCK_THRESHOLDS_MM)))
    return out, len(x)


def format_table(results, noise_mm):
    rows = ["| data | method | rotation error, deg (all 21 / 15 finger bones) | FK joint error, mm | joints within limits |",
            "|---|---|---|---|---|"]
    for (data, method), m in results.items():
        if method == "(frames)":
            continue
        rot = f"{m['rot_deg']:.2f} / {m['rot_finger_deg']:.2f}" if "rot_deg" in m else "n/a (no true rotations)"
        rows.append(f"| {data} | {method} | {rot} | {m['fk_mm']:.2f} | {m['limits_pct']:.2f}% |")
    rows.append("")
    rows.append(f"Emulated detector noise put in: {noise_mm:.2f} mm mean joint error (reference bone = 95 mm).")
    if ("real held-out", "(frames)") in results:
        rows.append(f"Real held-out frames: {results['real held-out', '(frames)']} ({', '.join(REAL_EVAL)}).")
    return "\n".join(rows)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m handmocap.training.eval_iknet", description=__doc__.splitlines()[0])
    p.add_argument("--model", default=None, help="int8 (default), float32 or an ONNX path")
    p.add_argument("--n", type=int, default=10000)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--pairs", help="an .npz of a detector's output on rendered crops (scripts/detnet_noisy_pairs.py): "
                                   "this table only")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    if args.pairs:
        results, n = evaluate_pairs(IKSolver.load(args.model, threads=args.threads), args.pairs)
        print(f"model: {model_path(args.model)}; {n} pairs from {args.pairs}")
        print("| input | mean joint error, mm | 3D AUC 20-50 mm |\n|---|---|---|")
        for method, (mm, area) in results.items():
            print(f"| {method} | {mm:.2f} | {area:.3f} |")
        return
    results, noise_mm = evaluate(IKSolver.load(args.model, threads=args.threads), args.n)
    print(f"model: {model_path(args.model)}")
    print(format_table(results, noise_mm))
    print(f"({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
