"""Speed of IKNet and of the ik node's per-hand maths on this CPU.

    python benchmarks/bench_iknet.py [--models int8 float32] [--threads 1] [--repeat 2000]

Per IKNet file (int8: models/iknet_int8.onnx, the default; float32: models/iknet.onnx; or a
path): `network`, the onnxruntime call alone, and `solve`, IKSolver.solve as the ik node
calls it (palm frame, input encoding, onnxruntime, quaternions back in camera axes), for one
hand and a batch of 8. Then the numpy steps after it, once: clamp_to_limits for one hand
inside its limits and one with joints outside, pose_fields (FK at the person's shape,
relative pose, Eq. 5 translation), and per model the whole per-hand maths of the ik node
(pose.pose_from_keypoints: solve + clamp + pose_fields); the analytic IK baseline last.

Each figure: median of `repeat` calls after a warm-up, as CPU time (time.process_time: what
the call costs, what an idle core would take) and wall time (which also counts waiting for
the CPU on a shared machine). The load average is printed first.
"""
import argparse
import os
import time

import numpy as np

from handmocap.perception.hand_model import HandModel
from handmocap.perception.ik_solver import IKSolver, analytic_ik, clamp_to_limits, iknet_inputs, model_path
from handmocap.perception.joint_limits import JointLimits
from handmocap.perception.kinematics import relative_to_global_quats
from handmocap.perception.pose import pose_fields, pose_from_keypoints
from handmocap.training.pose_data import PoseSampler, corrupt_joints


def median_ms(fn, repeat):
    """(CPU ms, wall ms): medians over `repeat` calls of fn() after 20 warm-up calls."""
    for _ in range(20):
        fn()
    cpu, wall = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return 1e3 * float(np.median(cpu)), 1e3 * float(np.median(wall))


def line(what, ms, per=1):
    cpu, wall = ms
    per_hand = f" ({cpu / per:.3f} ms/hand CPU)" if per > 1 else ""
    return f"{what}: {cpu:.3f} ms CPU, {wall:.3f} ms wall{per_hand}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", nargs="+", default=["int8", "float32"], help="int8, float32 or ONNX paths")
    ap.add_argument("--threads", nargs="+", type=int, default=[1], help="onnxruntime intra-op threads to try")
    ap.add_argument("--repeat", type=int, default=2000)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f}")
    model = HandModel.load()
    limits = JointLimits.for_model(model)
    d = PoseSampler(model).sample(8, np.random.default_rng(0))
    rest = d["rest"][0]
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    hand = {"track_id": 0, "handedness": "right", "score": 1.0, "xyz_rel": d["xyz"][0],
            "uv": np.full((21, 2), 320.0) + 40 * d["xyz"][0, :, :2]}
    for name in args.models:
        print(f"model: {model_path(name)}")
        for threads in args.threads:
            solver = IKSolver.load(name, threads=threads, model=model)
            for n in (1, 8):
                xyz = d["xyz"][:n]
                features, _ = iknet_inputs(xyz, rest)
                net = median_ms(lambda: solver.session.run(None, {solver.input_name: features}), args.repeat)
                total = median_ms(lambda: solver.solve(xyz, rest), args.repeat)
                print(f"  {threads} thread(s), batch {n}: " + line("network", net, n) + "; " + line("solve", total, n))
        solver = IKSolver.load(name, threads=1, model=model)
        ms = median_ms(lambda: pose_from_keypoints(hand, K, None, solver, model, limits=limits), args.repeat // 4)
        print("  " + line("ik node maths per hand (solve, clamp_to_limits, pose_fields; 1 thread)", ms))
    quats = d["quats"][:1]
    lo, hi = limits.limits[..., 0], limits.limits[..., 1]           # sampled poses may touch a limit
    inside = relative_to_global_quats(limits.pose_from_angles((lo + hi)[None] / 2, d["pose16"][:1, 0]))
    noisy = analytic_ik(corrupt_joints(d["xyz"][:1], np.random.default_rng(1), sigma_max=0.15), rest)
    outside = int((~limits.within(noisy, 0.0)).sum())
    print(line("clamp_to_limits, 1 hand inside its limits",
               median_ms(lambda: clamp_to_limits(inside, limits), args.repeat)))
    print(line(f"clamp_to_limits, 1 hand with {outside} joints outside",
               median_ms(lambda: clamp_to_limits(noisy, limits), args.repeat)))
    print(line("pose_fields (FK, relative pose, Eq. 5), 1 hand",
               median_ms(lambda: pose_fields(hand, quats[0], np.zeros(model.num_betas), K, model), args.repeat)))
    print(line("analytic IK, batch 1", median_ms(lambda: analytic_ik(d["xyz"][:1], rest), args.repeat // 4)))


if __name__ == "__main__":
    main()
