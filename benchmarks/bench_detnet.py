"""DetNet throughput in onnxruntime on this CPU: crops/s for batch 1 and 2, 1 and 2 threads.

    python benchmarks/bench_detnet.py [--model int8|float32|F.onnx] [--seconds 3]

Prints a table (median latency per call, crops/s from it, and the 10th percentile, which
is what the model does when the shared machine leaves it alone) and `uptime`, since the
figures depend on what else runs on the 2 cores.
"""
import argparse
import subprocess
import time

import numpy as np

from handmocap.perception.detnet_runner import detnet_path


def bench(path, batch, threads, seconds):
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = threads, 1
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    x = np.random.default_rng(0).random((batch, 3, 128, 128), dtype=np.float32)
    for _ in range(10):
        sess.run(None, {"image": x})
    times, end = [], time.perf_counter() + seconds
    while time.perf_counter() < end:
        t = time.perf_counter()
        sess.run(None, {"image": x})
        times.append(time.perf_counter() - t)
    return np.median(times), np.percentile(times, 10), len(times)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default=None, help="int8 (default: what the detector runs), float32 or an ONNX path")
    p.add_argument("--seconds", type=float, default=3.0)
    args = p.parse_args()
    args.model = detnet_path(args.model)
    print(f"{args.model} ({args.model.stat().st_size / 1e6:.2f} MB)")
    print(f"{'batch':>5} {'threads':>7} {'median ms':>10} {'crops/s':>8} {'p10 ms':>8} {'crops/s@p10':>11} {'calls':>6}")
    for batch in (1, 2):
        for threads in (1, 2):
            med, p10, n = bench(args.model, batch, threads, args.seconds)
            print(f"{batch:>5} {threads:>7} {med * 1e3:>10.2f} {batch / med:>8.0f} {p10 * 1e3:>8.2f} "
                  f"{batch / p10:>11.0f} {n:>6}")
    print("uptime:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())


if __name__ == "__main__":
    main()
