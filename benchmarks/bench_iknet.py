"""Speed of IKNet in onnxruntime on this CPU: one hand and a batch of 8, 1 and 2 threads.

    python benchmarks/bench_iknet.py [--model models/iknet.onnx] [--repeat 2000]

`solve` is IKSolver.solve as the ik node calls it (palm frame, input encoding, onnxruntime,
quaternions back in camera axes); `network` is the onnxruntime call alone. Also the
analytic IK baseline and the ik node's per-hand maths (pose_from_keypoints). Median of
`repeat` calls after a warm-up, so other processes' bursts on a shared CPU count less.
"""
import argparse
import importlib
import time

import numpy as np

from handmocap.hand_model import HandModel
from handmocap.ik_solver import DEFAULT_MODEL, IKSolver, analytic_ik, iknet_inputs
from handmocap.pose_data import PoseSampler


def median_ms(fn, repeat):
    for _ in range(20):
        fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(DEFAULT_MODEL))
    ap.add_argument("--repeat", type=int, default=2000)
    args = ap.parse_args()
    model = HandModel.load()
    d = PoseSampler(model).sample(8, np.random.default_rng(0))
    rest = d["rest"][0]
    print(f"model: {args.model}")
    for threads in (1, 2):
        solver = IKSolver.load(args.model, threads=threads)
        for n in (1, 8):
            xyz = d["xyz"][:n]
            features, _ = iknet_inputs(xyz, rest)
            total = median_ms(lambda: solver.solve(xyz, rest), args.repeat)
            net = median_ms(lambda: solver.session.run(None, {solver.input_name: features}), args.repeat)
            print(f"IKNet, {threads} thread(s), batch {n}: solve {total:.3f} ms ({total / n:.3f} ms/hand), "
                  f"network {net:.3f} ms ({net / n:.3f} ms/hand)")
    print(f"analytic IK, batch 1: {median_ms(lambda: analytic_ik(d['xyz'][:1], rest), args.repeat // 4):.3f} ms")
    ik = importlib.import_module("handmocap.nodes.ik")
    solver = IKSolver.load(args.model, threads=1)
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    hand = {"track_id": 0, "handedness": "right", "score": 1.0, "xyz_rel": d["xyz"][0],
            "uv": np.full((21, 2), 320.0) + 40 * d["xyz"][0, :, :2]}
    ms = median_ms(lambda: ik.pose_from_keypoints(hand, K, None, solver, model), args.repeat // 4)
    print(f"ik node maths per hand (IKNet 1 thread + pose, FK, translation): {ms:.3f} ms")


if __name__ == "__main__":
    main()
