"""Where a DetNet file's time goes: onnxruntime's own profiler, node time summed by the part of
the network each node's name says (the presence branch, the trunk, the rest).

    python research/detnet_node_time.py models/detnet_lite0_palm_int8.onnx runs/detnet/s64_branch_f/int8.onnx [--crops 300]

One thread, one crop a run, the same random crop every run. The profiler adds its own cost to
every node, so the totals are above a plain run's time: compare parts and files with each
other, not with bench_detnet.py's figures. Two files read one after the other share the
machine's state of that minute, which bench runs an hour apart do not.
"""
import argparse
import collections
import json
import os
import tempfile

import numpy as np

PARTS = (("presence_branch", "presence branch"), ("backbone", "trunk"), ("trunk", "trunk"))


def node_ms(path, crops):
    """{part: profiled ms a crop} for the DetNet file `path`, over `crops` runs."""
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads, so.enable_profiling = 1, True
    so.profile_file_prefix = os.path.join(tempfile.mkdtemp(prefix="detnet_prof"), "p")
    session = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    side = session.get_inputs()[0].shape[-1]
    x = np.random.default_rng(0).random((1, 3, side, side), dtype=np.float32)
    for _ in range(crops):
        session.run(None, {session.get_inputs()[0].name: x})
    events = json.load(open(session.end_profiling()))
    total = collections.Counter()
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            part = next((label for key, label in PARTS if key in e["name"]), "heads and the rest")
            total[part] += e["dur"] / 1000 / crops
    return total


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", nargs="+")
    p.add_argument("--crops", type=int, default=300)
    args = p.parse_args()
    print("| file | trunk | presence branch | heads and the rest | all (profiled ms a crop) |\n|---|---|---|---|---|")
    for path in args.files:
        t = node_ms(path, args.crops)
        print(f"| {path} | {t['trunk']:.2f} | {t['presence branch']:.2f} | {t['heads and the rest']:.2f} | "
              f"{sum(t.values()):.2f} |", flush=True)


if __name__ == "__main__":
    main()
