"""The one way the project opens its ONNX models (CPU, onnxruntime; no torch at run time)."""
import hashlib
import re
from pathlib import Path


def open_session(path: Path, what: str, made_by: str, threads: int = 1):
    """An onnxruntime CPU session of `path`, `threads` intra-op threads (1 is fastest per call
    on a busy 2-core machine); a missing file is one clear error naming it and the command
    that makes it (`made_by`); a file onnxruntime cannot load (corrupt, half-written while a
    training run exports it) is one ValueError naming it."""
    import onnxruntime as ort   # imported here: nodes that never run a model start faster
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} model {path} not found; make it with `{made_by}` "
                                f"(or pass the path of an exported file)")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as e:   # onnxruntime's own exception types (InvalidProtobuf, Fail, ...) are no OSError
        reason = re.sub(r"^\[ONNXRuntimeError\] : \d+ : ", "", str(e).strip().splitlines()[0] if str(e).strip() else "")
        raise ValueError(f"{what} model {path} cannot be loaded (corrupt, cut short, or not an ONNX model): "
                         f"{reason[:200] or type(e).__name__}; make it again with `{made_by}`") from None


def file_sha256(path) -> str:
    """Hex SHA-256 of a file (the float model a quantized one was made from)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def stale_quantization(session, path, made_by: str):
    """A line saying that the int8 file `path` (its metadata `source_name`, `source_sha256`)
    was made from another float32 file than the one beside it (retrained, not quantized
    again with `made_by`), else None."""
    meta = session.get_modelmeta().custom_metadata_map
    source = Path(path).parent / meta.get("source_name", "")
    if "source_sha256" not in meta or not source.is_file() or source == Path(path):
        return None
    if file_sha256(source) == meta["source_sha256"]:
        return None
    return (f"{path} was quantized from another {source.name} than the one beside it: make it again with "
            f"`{made_by}` (or load \"float32\")")


def quantize_static_int8(src, out, input_name: str, inputs, batch: int, op_types, keep_float=lambda node: False,
                         extra_options=None, note: str = "", reduce_range=False):
    """Write the static int8 copy of the float32 ONNX file `src` to `out` and return it (an
    onnx ModelProto): onnxruntime's quantize_static, QDQ format (fused into int8 kernels at
    load), weights int8 symmetric per output channel (in 7 bits with `reduce_range`: without
    AVX-512 VNNI, onnxruntime's uint8 x int8 kernels add pairs of products in int16, which
    8-bit weights can overflow), activations uint8 with MinMax ranges
    from `inputs` (M, ...) float32 fed to `input_name` `batch` rows at a time. Nodes of
    `op_types` are quantized unless keep_float(node); the file records its source
    (metadata source_name, source_sha256: see stale_quantization) and `note`."""
    import tempfile

    import numpy as np
    import onnx
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)
    src, out = Path(src), Path(out)
    model = onnx.load(str(src))
    for i, node in enumerate(model.graph.node):          # exporters leave names empty; the quantizer needs them
        node.name = node.name or f"{node.op_type}_{i}"
    inputs = np.asarray(inputs, np.float32)

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.batches = iter(inputs[i:i + batch] for i in range(0, len(inputs), batch))

        def get_next(self):
            rows = next(self.batches, None)
            return None if rows is None else {input_name: rows}

    excluded = [node.name for node in model.graph.node if keep_float(node)]
    with tempfile.TemporaryDirectory() as tmp:
        named = Path(tmp) / "named.onnx"
        onnx.save(model, str(named))
        quantize_static(str(named), str(out), Reader(), quant_format=QuantFormat.QDQ,
                        op_types_to_quantize=list(op_types), nodes_to_exclude=excluded, per_channel=True,
                        weight_type=QuantType.QInt8, activation_type=QuantType.QUInt8, reduce_range=reduce_range,
                        calibrate_method=CalibrationMethod.MinMax, extra_options=extra_options or {})
    quantized = onnx.load(str(out))
    quantized.producer_name, quantized.doc_string = model.producer_name, (model.doc_string + " (static int8)").strip()
    onnx.helper.set_model_props(quantized, {"source_sha256": file_sha256(src), "source_name": src.name,
                                            "quantization": note})
    onnx.save(quantized, str(out))
    return quantized
