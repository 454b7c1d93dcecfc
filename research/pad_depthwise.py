"""Pad the depthwise convs of exported DetNet files to multiples of 8 channels, in place
(onnx_models.pad_depthwise_convs: the same function, faster on onnxruntime's CPU kernels).

    python research/pad_depthwise.py models/detnet.onnx models/detnet_int8.onnx

`handtrain detnet` exports padded files since session 16; this brings older ones up to date.
A file already padded is left as it is. An int8 file made from a float file (its metadata
`source_sha256`, see onnx_models.stale_quantization) still names that file afterwards: when
it matched its source before, it is given the padded source's hash, so the pair stays a
pair. Give the float file first. Prints, per file, how many convs were padded and the
largest output difference against the file as it was, on random crops.
"""
import argparse
import tempfile
from pathlib import Path

import numpy as np
import onnx

from handmocap.perception.onnx_models import file_sha256, open_session, pad_depthwise_convs


def largest_difference(before: Path, after: Path) -> float:
    """Max |output difference| of two DetNet files on 8 random crops."""
    x = np.random.default_rng(0).random((8, 3, 128, 128), dtype=np.float32)
    a, b = (open_session(p, "DetNet", "handtrain detnet").run(None, {"image": x}) for p in (before, after))
    return max(float(np.abs(u - v).max()) for u, v in zip(a, b))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", nargs="+", type=Path)
    args = p.parse_args()
    new_sha = {}                                   # file name -> (sha before, sha after)
    for path in args.files:
        model = onnx.load(str(path))
        meta = {m.key: m.value for m in model.metadata_props}
        source = meta.get("source_name")
        if source in new_sha and meta.get("source_sha256") == new_sha[source][0]:
            onnx.helper.set_model_props(model, {**meta, "source_sha256": new_sha[source][1]})
        n = pad_depthwise_convs(model)
        onnx.checker.check_model(model)
        before = file_sha256(path)
        with tempfile.TemporaryDirectory() as tmp:
            old = Path(tmp) / path.name
            old.write_bytes(path.read_bytes())
            onnx.save(model, str(path))
            diff = largest_difference(old, path)
        new_sha[path.name] = (before, file_sha256(path))
        print(f"{path}: {n} depthwise conv(s) padded; largest output difference {diff:.2g}")


if __name__ == "__main__":
    main()
