"""Static int8 IKNet: models/iknet.onnx -> models/iknet_int8.onnx.

    python -m handmocap.training.quantize_iknet [--src models/iknet.onnx] [--out models/iknet_int8.onnx] [--n 16384]

Why: at batch 1 the float32 network streams 22 MB of weights per hand (about 1 ms on this
CPU); int8 weights are a quarter of that. Dynamic quantization (`handtrain iknet --int8`)
is as fast but takes its activation ranges from each batch, so a hand's result depended on
the other hands in the batch. Here every range is fixed in the file, so each row of a batch
is computed on its own: the same input gives the same output alone or in any batch.

How (onnxruntime.quantization.quantize_static, QDQ format, which onnxruntime fuses into
int8 QGemm kernels at load):
* calibration data: inputs made exactly as training batches are (pose_data.BatchMaker:
  pose samples, emulated detector errors, the REAL_TRAIN clips when /work/shared is
  there), from their own seed CALIB_SEED; never the evaluation poses or REAL_EVAL clips;
* the first layer (252 -> 1024, 1 MB of the 22) stays float32: its input, 252 features
  with very different ranges (joints up to ~2, some bone components ~0.01), was the largest
  quantization error with one uint8 scale (0.10 deg more rotation error than float32 on
  the validation poses against 0.03 deg without it), and it costs 0.03 ms;
* layers 2-7: weights int8, symmetric, per output channel; their inputs (sigmoid outputs)
  uint8 with ranges from the calibration set (MinMax, `--pin-ranges`: the sigmoid's
  [0, 1] instead);
* the Gemm outputs stay float32 (sigmoid in float, the last layer's raw quaternions
  in float): quantizing the pre-sigmoid sums cost 0.04 deg more for no speed.
The result carries the source file's SHA-256 (metadata `source_sha256`) so that
IKSolver.load can warn when iknet.onnx was retrained and this file not made again.
"""
import argparse
from pathlib import Path

import numpy as np

from handmocap.perception.ik_solver import FLOAT32_MODEL, INT8_MODEL, NUM_INPUTS
from handmocap.perception.onnx_models import quantize_static_int8

CALIB_SEED = 31_415_926          # own seed: not training ([seed, it]), validation or evaluation
CALIB_BATCH = 256


def calibration_features(n, model=None, data_root=None, seed=CALIB_SEED):
    """(n, 252) float32 network inputs mixed as training batches are (BatchMaker), own seed."""
    from handmocap.perception.hand_model import HandModel
    from handmocap.training.pose_data import REAL_TRAIN, SHARED_DATA, BatchMaker, PositionPairs, load_real_sequences
    model = HandModel.load() if model is None else model
    sequences = load_real_sequences(REAL_TRAIN, SHARED_DATA if data_root is None else data_root)
    real = PositionPairs.from_sequences(sequences, model) if sequences else None
    maker = BatchMaker(model, real_pairs=real)
    batches = [maker.make(CALIB_BATCH, np.random.default_rng([seed, i]))["features"]
               for i in range(-(-n // CALIB_BATCH))]
    return np.concatenate(batches)[:n]


def quantize(src=FLOAT32_MODEL, out=INT8_MODEL, n=16384, data_root=None, features=None, pin_ranges=False):
    """Write the static int8 copy of `src` to `out`; returns the calibrated ranges {tensor:
    (lo, hi)} of the quantized activations. features: (M, 252) calibration inputs instead
    of calibration_features(n); pin_ranges: [0, 1] for every sigmoid output instead."""
    import onnx
    src, out = Path(src), Path(out)
    features = calibration_features(n, data_root=data_root) if features is None else np.asarray(features, np.float32)
    if features.shape[1:] != (NUM_INPUTS,):
        raise ValueError(f"calibration features must be (M, {NUM_INPUTS}), got {features.shape}")
    graph = onnx.load(str(src)).graph
    first = next(node.output[0] for node in graph.node if node.op_type == "Gemm" and node.input[0] == "features")
    hidden = [node.output[0] for node in graph.node if node.op_type == "Sigmoid"]
    overrides = {h: [{"rmin": np.float32(0.0), "rmax": np.float32(1.0)}] for h in hidden} if pin_ranges else {}
    quantized = quantize_static_int8(
        src, out, "features", features, CALIB_BATCH, ["Gemm"], keep_float=lambda node: node.output[0] == first,
        extra_options={"OpTypesToExcludeOutputQuantization": ["Gemm"], "TensorQuantOverrides": overrides},
        note=f"static int8 QDQ, first layer float32, {len(features)} calibration inputs (seed {CALIB_SEED})")
    return activation_ranges(quantized, hidden)


def activation_ranges(onnx_model, tensors):
    """{tensor: (lo, hi)} that the uint8 scale and zero point of each quantized tensor cover."""
    from onnx import numpy_helper
    inits = {i.name: numpy_helper.to_array(i) for i in onnx_model.graph.initializer}
    ranges = {}
    for t in tensors:
        scale, zero = inits.get(f"{t}_scale"), inits.get(f"{t}_zero_point")
        if scale is not None and zero is not None:
            ranges[t] = (float(scale * (0 - int(zero))), float(scale * (255 - int(zero))))
    return ranges


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m handmocap.training.quantize_iknet", description=__doc__.splitlines()[0])
    p.add_argument("--src", type=Path, default=FLOAT32_MODEL, help="float32 IKNet (default %(default)s)")
    p.add_argument("--out", type=Path, default=INT8_MODEL, help="int8 output (default %(default)s)")
    p.add_argument("--n", type=int, default=16384, help="calibration inputs")
    p.add_argument("--data", type=Path, default=None, help="real data pack for the REAL_TRAIN share")
    p.add_argument("--pin-ranges", action="store_true", help="sigmoid outputs quantized over [0, 1], not calibrated")
    args = p.parse_args(argv)
    ranges = quantize(args.src, args.out, args.n, args.data, pin_ranges=args.pin_ranges)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.1f} MB) from {args.src}; {args.n} calibration inputs; "
          "hidden ranges " + ", ".join(f"[{lo:.3f}, {hi:.3f}]" for lo, hi in ranges.values()))


if __name__ == "__main__":
    main()
