"""Static int8 DetNet: models/detnet.onnx -> models/detnet_int8.onnx, and both measured.

    python -m handmocap.training.quantize_detnet [--src models/detnet.onnx] [--out models/detnet_int8.onnx]
                                        [--n 1024] [--data 'runs/detnet_data/synth_train_*']
    python -m handmocap.training.quantize_detnet --compare models/detnet.onnx models/detnet_int8.onnx
    python -m handmocap.training.quantize_detnet --src runs/detnet/grey/final.onnx --out models/detnet_grey_int8.onnx --grey
    python -m handmocap.training.quantize_detnet --side-only [models/detnet_int8.onnx]
    python -m handmocap.training.quantize_detnet --fold-pads models/detnet_lite0_int8.onnx

Why: DetNet is the largest cost of a tracked frame. With its convolutions in int8
(onnxruntime's QLinearConv / VNNI kernels) the fast-deep network takes about 1.4 ms per
crop on this CPU instead of 2.3 (a quiet hour; docs/models_history.md), and the file is half
the size.

How (onnxruntime.quantization.quantize_static, QDQ format, fused into int8 kernels at load):
* calibration crops: batches made exactly as training batches are (detnet_batches.BatchMaker:
  synthetic training shards, real training crops, negatives, colour jitter left out) from
  their own seed CALIB_SEED; never the held-out synthetic shard, the held-out real crops or
  an evaluation split;
* every Conv (weights int8, symmetric, per output channel, in 7 bits: on a CPU without
  AVX-512 VNNI, onnxruntime's uint8 x int8 kernels sum pairs of products in int16, which
  full 8-bit weights can overflow; on an AVX2 AMD EPYC the 7-bit copy is the nearer to
  float32: median 2D gap 0.51 crop px against 0.83, heatmap peaks 0.10 at most against
  0.18, session 13; activations uint8, MinMax ranges) and the residual Adds and ReLUs
  between them, so that activations stay int8 from one convolution to the next, except
  the delta and location heads (KEEP_FLOAT): their inputs concatenate features,
  coordinate channels, sigmoid heatmaps and delta maps of very different ranges, and one
  uint8 scale over them cost 0.9 mm of 3D error (held-out synthetic; 0.06 mm with them
  float32). The read-out after the heads (argmax, sub-pixel parabola, location look-up)
  and the presence / handedness Gemms stay float32 too.
`--fold-pads` folds lite0's "SAME" Pads into the quantized convolutions of a file made before
session 47 (onnx_models.fold_same_pads; quantizing now does it): the same outputs, a fifth less
time a crop. `--side-only` writes the part of a DetNet file its handedness head needs (`<stem>_side.onnx`
beside it: what a pair's side network runs, detnet_runner.SideNetwork); quantizing into a file
that has such a part beside it writes the part again.
`--compare` prints the training run's held-out metrics (detnet_eval.validate: synthetic
2D px and 3D mm, howiema 001 L8/R8, video tails, handedness, presence) for each file, so a
quantized file is judged on the same numbers as the float one it came from.
"""
import argparse
import json
from pathlib import Path

import numpy as np

from handmocap.perception.detnet_runner import DETNET_FLOAT32, DETNET_INT8, DetNetRunner, head_only_path
from handmocap.perception.hand_finder import greyed
from handmocap.perception.onnx_models import check_session, file_sha256, fold_same_pads_file, quantize_static_int8

CALIB_SEED = 27_182_818          # own seed: not training ([seed, it]), validation or evaluation
# Clip (ReLU6), Pad ("SAME" padding) and Resize (the FPN's upsampling): the lite0 backbone's; left float they cost a
# dequantize and requantize each (lite0: 1.44 against 1.21 ms a crop, one thread; session 35)
QUANTIZED_OPS = ["Conv", "Add", "Relu", "Clip", "Pad", "Resize"]
KEEP_FLOAT = ("delta_head", "loc_head")


def calibration_crops(n, data="runs/detnet_data/synth_train_*", shared=None, seed=CALIB_SEED, grey=False):
    """(n,128,128,3) uint8 RGB crops mixed as training batches are (no colour jitter); grey:
    in grey (for a network that runs on grey frames)."""
    from handmocap.training.pose_data import SHARED_DATA
    from handmocap.training.detnet_batches import BatchMaker
    from handmocap.training.detnet_data import load_real, load_synth, synth_dirs
    synth = load_synth(synth_dirs([data]), 8192)
    if synth is None:
        raise SystemExit(f"no synthetic training shards match {data}: make one with `handsynth generate -n 8192 "
                         f"-o runs/detnet_data/synth_train_0 --seed 1000`")
    real = load_real(SHARED_DATA if shared is None else shared)
    maker = BatchMaker(synth, real, share_real=0.3, share_neg=0.15, share_left=0.3)
    crops = np.concatenate([maker.make(64, np.random.default_rng([seed, i]))["image"]
                            for i in range(-(-n // 64))])[:n]
    return greyed(crops[..., ::-1]) if grey else crops


def quantize(src, out, crops, keep_float=KEEP_FLOAT):
    """Write the static int8 copy of the float DetNet `src` to `out`, calibrated on `crops`
    (M,128,128,3) uint8 RGB; nodes whose name contains one of `keep_float` stay float32."""
    images = np.ascontiguousarray(crops.transpose(0, 3, 1, 2), dtype=np.float32) / 255.0
    quantize_static_int8(src, out, "image", images, 32, QUANTIZED_OPS,
                         keep_float=lambda node: any(k in node.name for k in keep_float), reduce_range=True,
                         note=f"static int8 QDQ ({', '.join(QUANTIZED_OPS)}; {', '.join(keep_float) or 'nothing'} "
                              f"float32), {len(crops)} calibration crops (seed {CALIB_SEED})")


def write_head_only(src, out=None, check_crops=8):
    """Write the part of the DetNet file `src` that its `handedness` output needs (onnx's
    Extractor: the backbone up to the head's branch and the head; not the heatmap, delta and
    location heads) to `out` (default head_only_path(src)), its metadata naming `src`
    (source_name, source_sha256: onnx_models.made_from_another); checks that it answers as
    `src` does, to the bit, on `check_crops` random crops. Returns out."""
    import onnx
    import onnx.utils
    src = Path(src)
    out = head_only_path(src) if out is None else Path(out)
    model = onnx.load(str(src))
    image = model.graph.input[0].name
    head = onnx.utils.Extractor(model).extract_model([image], ["handedness"])
    head.producer_name = model.producer_name
    head.doc_string = f"{model.doc_string} (the handedness head's part alone)".strip()
    onnx.helper.set_model_props(head, {"source_name": src.name, "source_sha256": file_sha256(src),
                                       "part": "handedness"})
    onnx.save(head, str(out))
    side = model.graph.input[0].type.tensor_type.shape.dim[-1].dim_value
    x = np.random.default_rng(0).random((check_crops, 3, side, side), dtype=np.float32)
    whole, part = (check_session(f).run(["handedness"], {image: x})[0] for f in (src, out))
    if not np.array_equal(whole, part):
        out.unlink()
        raise RuntimeError(f"the handedness part of {src} does not answer as the whole network does "
                           f"(largest gap {np.abs(whole - part).max():.3g}); nothing written")
    return out


class OnnxNet:
    """An exported DetNet file in the shape detnet_eval.validate expects of a network
    (`predict`), read out as exported (one refine)."""

    def __init__(self, path, threads=1):
        self.runner = DetNetRunner.load(path, threads)

    def predict(self, images, batch=128):
        outs = [self.runner(images[i:i + batch]) for i in range(0, len(images), batch)]
        cat = {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}
        return (cat["uv"], cat["xyz"], cat["confidence"]), cat["presence"], cat["handedness"]


def heldout_sets(shared=None, val="runs/detnet_data/synth_val", upright=False, grey=False):
    """The training run's held-out synthetic and real sets (detnet_eval.validate's inputs);
    upright: each crop turned by the quarter turn the detector would give it (quarter_turned);
    grey: every crop in grey."""
    from handmocap.training.pose_data import SHARED_DATA
    from handmocap.training.detnet_data import load_real
    from handmocap.training.detnet_eval import real_val_set, synth_val_set
    sval = synth_val_set(val) if (Path(val) / "meta.json").exists() else None
    rval = real_val_set(load_real(SHARED_DATA if shared is None else shared))
    if upright:
        sval, rval = (quarter_turned(v) if v is not None else None for v in (sval, rval))
    if grey:
        sval, rval = ({k: greyed(v[..., ::-1]) if k in ("image", "raw", "neg") else v for k, v in s.items()}
                      if s is not None else None for s in (sval, rval))
    return sval, rval


def quarter_turned(crops):
    """A held-out set (image (N,S,S,3) with uv (N,21,2), optionally xyz (N,21,3) and the
    unmirrored `raw` images) with each crop turned as the detector's `upright_step` 90 turns
    it: by the quarter turns nearest to its hand's angle (crops.hand_angle), so the hand
    is within 45 degrees of upright. A turn counter-clockwise takes a point (x, y) to
    (y, S-1-x) and a 3D offset (x, y, z) to (y, -x, z); `raw` turns the mirror way."""
    from handmocap.perception.crops import hand_angle
    out = dict(crops)
    size = crops["image"].shape[1]
    k = np.round(hand_angle(crops["uv"]) / (np.pi / 2)).astype(int) % 4
    for key in ("image", "raw", "uv", "xyz"):
        if key in crops:
            out[key] = crops[key].copy()
    for i in np.flatnonzero(k):
        out["image"][i] = np.rot90(crops["image"][i], k[i])
        if "raw" in crops:    # the unmirrored crop of a mirrored (left) hand turns the other way
            left = "right" in crops and crops["right"][i] < 0.5
            out["raw"][i] = np.rot90(crops["raw"][i], -k[i] if left else k[i])
        for _ in range(k[i]):
            out["uv"][i] = np.stack([out["uv"][i][:, 1], size - 1 - out["uv"][i][:, 0]], -1)
            if "xyz" in crops:
                out["xyz"][i] = np.stack([out["xyz"][i][:, 1], -out["xyz"][i][:, 0], out["xyz"][i][:, 2]], -1)
    return out


def heldout_metrics(path, sets=None):
    """detnet_eval.validate's held-out metrics of an exported DetNet file; sets: heldout_sets()."""
    from handmocap.training.detnet_eval import validate
    return validate(OnnxNet(path), *(sets or heldout_sets()))


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m handmocap.training.quantize_detnet", description=__doc__.splitlines()[0])
    p.add_argument("--src", type=Path, default=DETNET_FLOAT32, help="float32 DetNet (default %(default)s)")
    p.add_argument("--out", type=Path, default=DETNET_INT8, help="int8 output (default %(default)s)")
    p.add_argument("--n", type=int, default=1024, help="calibration crops")
    p.add_argument("--data", default="runs/detnet_data/synth_train_*", help="synthetic training shards (glob)")
    p.add_argument("--compare", nargs="+", type=Path, metavar="ONNX",
                   help="print the held-out metrics of these files instead of quantizing")
    p.add_argument("--upright", action="store_true",
                   help="with --compare: each held-out crop turned by quarter turns as the detector turns it")
    p.add_argument("--grey", action="store_true",
                   help="calibrate on grey crops (a network for grey frames); with --compare: grey held-out crops")
    p.add_argument("--fold-pads", nargs="+", type=Path, metavar="ONNX",
                   help="fold the \"SAME\" Pads of these int8 files (lite0's) into their convolutions, in place, "
                        "where the outputs stay the same to the bit (quantizing does it too)")
    p.add_argument("--side-only", nargs="?", type=Path, const=DETNET_INT8, metavar="ONNX",
                   help="write the part of ONNX (default %(const)s) that its handedness head needs, as "
                        "<stem>_side.onnx beside it, instead of quantizing")
    args = p.parse_args(argv)
    if args.fold_pads:
        for path in args.fold_pads:
            print(f"{path}: {fold_same_pads_file(path)} Pads folded into its convolutions")
        return
    if args.side_only:
        out = write_head_only(args.side_only)
        print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB): the handedness head of {args.side_only}")
        return
    if args.compare:
        sets = heldout_sets(upright=args.upright, grey=args.grey)
        for path in args.compare:
            metrics = heldout_metrics(path, sets)
            print(json.dumps({"model": str(path), **{k: round(v, 4) for k, v in metrics.items()}}))
        return
    quantize(args.src, args.out, calibration_crops(args.n, args.data, grey=args.grey))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB) from {args.src}; {args.n} calibration crops")
    if head_only_path(args.out).is_file():     # its side part, in step with it
        print(f"wrote {write_head_only(args.out)}: its handedness head's part")


if __name__ == "__main__":
    main()
