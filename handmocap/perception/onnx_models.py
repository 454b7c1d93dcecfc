"""The one way the project opens its ONNX models (CPU, onnxruntime; no torch at run time)."""
import contextlib
import functools
import hashlib
import os
import platform
import re
import threading
from pathlib import Path

# Where onnxruntime's optimized copy of each model is kept, so that a node's later starts skip
# the graph optimizations (a respawned detector's three DetNets load in ~0.05 s against ~0.22;
# issue 49's drill wants poses back within 1 s of a kill): $HANDMOCAP_ONNX_CACHE, else
# $XDG_CACHE_HOME/handmocap/onnx, else ~/.cache/handmocap/onnx; "none" keeps none. A copy is
# named by its source file's SHA-256, onnxruntime's version and this CPU (onnxruntime lays an
# optimized graph out for the CPU it ran on), so a retrained file or another machine never
# reads a stale one; the folder may be deleted at any time. It keeps the ONNX_CACHE_FILES
# copies last used (a training run's validations each load a new file: ~4 MB a copy).
ONNX_CACHE_ENV = "HANDMOCAP_ONNX_CACHE"
ONNX_CACHE_FILES = 32


def _allowed_cpus() -> list[int] | None:
    """The CPUs the calling thread may run on (its affinity: a container's limit, not the
    machine's count), sorted; None where the platform has no affinity call."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:          # (no affinity call on this platform)
        return None


def cores() -> int:
    """CPU cores this process may run on (_allowed_cpus, else the machine's count). Where there
    is one, nothing is read on a second thread: it would only wait its turn."""
    cpus = _allowed_cpus()
    return len(cpus) if cpus is not None else os.cpu_count() or 1


@functools.lru_cache(maxsize=1)
def cpu_split() -> tuple[frozenset, frozenset] | None:
    """(the CPUs a frame's own thread runs on while it reads a frame, the one CPU helper threads
    run on: a second network read, the finder beside the crops), from this process's CPUs when
    first asked; None with one CPU or no affinity call on this platform.

    Why: at 30 fps the threads sleep between frames, and Linux wakes a helper on the CPU of the
    thread that woke it, which is busy with the frame's own reads: the helper waited there while
    the other core idled. Paced at 30 fps, a lite0 read with the side network's read of two crops
    beside it took 7.0 ms unpinned (the helper started 1.5 ms after it was handed the work, p90
    3.5-4.4) and 4.8 ms with the two threads kept apart (0.7; docs/experiment_log.md, session 50)."""
    cpus = _allowed_cpus()
    return (frozenset(cpus[:-1]), frozenset(cpus[-1:])) if cpus is not None and len(cpus) > 1 else None


def _set_cpus(cpus) -> bool:
    """Keep the calling thread on `cpus`; False where the system refuses (CPUs taken away since
    cpu_split looked): the thread then runs where it may, as without pinning."""
    try:
        os.sched_setaffinity(0, cpus)
        return True
    except OSError:
        return False


def keep_on_helper_cpu() -> None:
    """Keep the calling thread on the helpers' CPU (cpu_split; a thread pool's initializer)."""
    split = cpu_split()
    if split:
        _set_cpus(split[1])


@contextlib.contextmanager
def off_helper_cpu():
    """The calling thread kept off the helpers' CPU inside the block, its CPUs as they were after
    it (a process the thread starts later, MediaPipe's in a benchmark say, inherits no pinning)."""
    split = cpu_split()
    before = os.sched_getaffinity(0) if split else None
    pinned = bool(split) and _set_cpus(split[0])
    try:
        yield
    finally:
        if pinned:
            _set_cpus(before)


_shared_arena = threading.Lock()
_shared_arena_made = False


def use_shared_arena(ort, opts) -> None:
    """Make the session of `opts` allocate from one memory arena shared by every session of the
    process (onnxruntime's environment allocator, registered on the first call): a session's
    own arena keeps its largest run's activations for good, so a process holding several
    networks (the detector holds six) held their sum; one arena holds about the largest
    (a tracker on a two-hand clip: 9 MB less, benchmarks/bench_memory.py)."""
    global _shared_arena_made
    with _shared_arena:
        if not _shared_arena_made:
            info = ort.OrtMemoryInfo("Cpu", ort.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0, ort.OrtMemType.DEFAULT)
            ort.create_and_register_allocator(info, ort.OrtArenaCfg(0, -1, -1, -1))   # onnxruntime's defaults
            _shared_arena_made = True
    opts.add_session_config_entry("session.use_env_allocators", "1")


def onnx_cache_dir() -> Path | None:
    """The folder of optimized copies (ONNX_CACHE_ENV), None when turned off."""
    given = os.environ.get(ONNX_CACHE_ENV)
    if given:
        return None if given.lower() == "none" else Path(given)
    home = os.path.expanduser("~")
    if not os.environ.get("XDG_CACHE_HOME") and home.startswith("~"):    # no home (a bare container): none
        return None
    return Path(os.environ.get("XDG_CACHE_HOME") or Path(home) / ".cache") / "handmocap" / "onnx"


@functools.cache
def _this_cpu() -> str:
    """What names this CPU for onnxruntime's layout choices: its model and instruction-set
    flags (Linux), else the platform's processor string. Read once a process (a detector
    opens five networks; /proc/cpuinfo is a line per core)."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = [line for line in f if line.startswith(("model name", "flags"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return f"{platform.machine()} {platform.processor()}"


def optimized_copy(path: Path, ort) -> Path | None:
    """Where the optimized copy of the model file `path` is or goes (onnx_cache_dir), None
    when the cache is off."""
    folder = onnx_cache_dir()
    if folder is None:
        return None
    key = hashlib.sha256(f"{file_sha256(path)} {ort.__version__} {_this_cpu()}".encode()).hexdigest()[:24]
    return folder / f"{Path(path).stem}-{key}.onnx"


def _session_options(ort, threads: int, optimize: bool):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize
                                     else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    # errors only: when onnxruntime folds lite0's "SAME" Pad nodes into its convolutions it
    # warns once per constant left unused (about 60 lines a load), which says nothing to a user
    opts.log_severity_level = 3
    use_shared_arena(ort, opts)
    return opts


def check_session(model):
    """An onnxruntime CPU session of `model` (a file or a serialized ModelProto), one thread,
    this module's options, not cached: what a rewrite's bit-equality check runs."""
    import onnxruntime as ort
    return ort.InferenceSession(str(model) if isinstance(model, Path) else model, _session_options(ort, 1, optimize=True),
                                providers=["CPUExecutionProvider"])


def open_session(path: Path, what: str, made_by: str, threads: int = 1):
    """An onnxruntime CPU session of `path`, `threads` intra-op threads (1 is fastest per call
    on a busy 2-core machine), from its optimized copy where one is cached (optimized_copy;
    made on the first load); a missing file is one clear error naming it and the command
    that makes it (`made_by`); a file onnxruntime cannot load (corrupt, half-written while a
    training run exports it) is one ValueError naming it."""
    import onnxruntime as ort   # imported here: nodes that never run a model start faster
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} model {path} not found; make it with `{made_by}` "
                                f"(or pass the path of an exported file)")
    copy = optimized_copy(path, ort)
    if copy is not None and copy.is_file():
        try:
            session = ort.InferenceSession(str(copy), _session_options(ort, threads, optimize=False),
                                           providers=["CPUExecutionProvider"])
            with contextlib.suppress(OSError):
                os.utime(copy)        # last used now: kept over older ones (_keep_last_used)
            return session
        except Exception:     # a copy gone bad (a disk error): made again below
            copy.unlink(missing_ok=True)
    opts = _session_options(ort, threads, optimize=True)
    written = None
    if copy is not None:
        try:
            copy.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
            if os.access(copy.parent, os.W_OK):
                written = copy.with_name(f".{copy.name}.{os.getpid()}.{threading.get_ident()}")
                opts.optimized_model_filepath = str(written)
        except OSError:       # a read-only home: no cache, the model loads as it always did
            written = None
    try:
        try:
            session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception:
            if written is None:
                raise
            written.unlink(missing_ok=True)    # (the copy could not be written: a full disk) once more, without
            written = None
            session = ort.InferenceSession(str(path), _session_options(ort, threads, optimize=True),
                                           providers=["CPUExecutionProvider"])
    except Exception as e:   # onnxruntime's own exception types (InvalidProtobuf, Fail, ...) are no OSError
        reason = re.sub(r"^\[ONNXRuntimeError\] : \d+ : ", "", str(e).strip().splitlines()[0] if str(e).strip() else "")
        raise ValueError(f"{what} model {path} cannot be loaded (corrupt, cut short, or not an ONNX model): "
                         f"{reason[:200] or type(e).__name__}; make it again with `{made_by}`") from None
    if written is not None:
        try:
            os.replace(written, copy)     # whole or not at all: another process may read it now
            _keep_last_used(copy.parent)
        except OSError:
            written.unlink(missing_ok=True)
    return session


def _keep_last_used(folder: Path, keep: int = ONNX_CACHE_FILES) -> None:
    """Delete all but the `keep` copies in `folder` used last (by modification time)."""
    copies = []
    for p in folder.glob("*.onnx"):
        with contextlib.suppress(OSError):       # (another process may delete one meanwhile)
            copies.append((p.stat().st_mtime, p))
    for _, p in sorted(copies, reverse=True)[keep:]:
        p.unlink(missing_ok=True)


def file_sha256(path) -> str:
    """Hex SHA-256 of a file (the float model a quantized one was made from)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def made_from_another(session, path) -> Path | None:
    """The file beside `path` that the model file `path` was made from (its metadata
    `source_name`, `source_sha256`: an int8 copy's float32 file, a part's whole network)
    where that file has changed since, else None (no such metadata, or no such file)."""
    meta = session.get_modelmeta().custom_metadata_map
    source = Path(path).parent / meta.get("source_name", "")
    if "source_sha256" not in meta or not source.is_file() or source == Path(path):
        return None
    return None if file_sha256(source) == meta["source_sha256"] else source


def stale_quantization(session, path, made_by: str):
    """A line saying that the int8 file `path` was made from another float32 file than the
    one beside it (retrained, not quantized again with `made_by`), else None."""
    source = made_from_another(session, path)
    if source is None:
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
    (metadata source_name, source_sha256: see stale_quantization) and `note`. "SAME" Pads
    before quantized convolutions are folded into them (fold_same_pads_file)."""
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
    if fold_same_pads_file(out, inputs[:batch]):       # "SAME" pads into the quantized convolutions
        quantized = onnx.load(str(out))
    return quantized


# single-input elementwise ops that may sit between a depthwise conv and the 1x1 conv after it:
# whatever they make of a padded (zero) channel, the 1x1 conv's zero weights take none of it
_ELEMENTWISE = {"Relu", "Clip", "LeakyRelu", "HardSigmoid", "HardSwish", "Sigmoid", "Tanh"}


def _attribute(node, name: str, default=None):
    """The value of the onnx node's attribute `name` (a string one as bytes), else `default`."""
    from onnx import helper
    return next((helper.get_attribute_value(a) for a in node.attribute if a.name == name), default)


def _readers(graph) -> dict:
    """{tensor name: the nodes of the onnx `graph` that read it}."""
    out = {}
    for node in graph.node:
        for name in node.input:
            out.setdefault(name, []).append(node)
    return out


def pad_depthwise_convs(model, multiple: int = 8) -> int:
    """Pad the channels of each float32 depthwise conv whose channel count is no multiple of
    `multiple` (and of the 1x1 conv that reads it) with zero channels, in place on the
    onnx ModelProto `model`; returns how many were padded. The function is unchanged: a Pad
    node appends zero input channels, their depthwise kernels and biases are zero, and the
    1x1 conv's weights for them are zero.

    Why: onnxruntime's CPU kernels run a depthwise conv in blocks of 8 channels (AVX2); with
    another count it falls back to a generic grouped conv, 2.5x slower (DetNet's delta and
    location heads: 119 and 182 channels at 16x16, 0.36 / 0.52 ms against 0.15 / 0.20 padded
    to 120 / 184; docs/models_history.md, "Speed"). Convs whose weights are not plain
    initializers (quantized ones) are left alone."""
    import numpy as np
    from onnx import helper, numpy_helper
    graph = model.graph
    inits = {t.name: t for t in graph.initializer}
    uses = _readers(graph)
    attr = _attribute

    def replace_init(name, array):
        inits[name].CopyFrom(numpy_helper.from_array(array.astype(np.float32), name))

    padded = 0
    for dw in [n for n in graph.node if n.op_type == "Conv"]:
        w = inits.get(dw.input[1])
        if w is None or len(uses.get(dw.input[1], [])) != 1:
            continue
        W = numpy_helper.to_array(w)
        c = W.shape[0]
        if attr(dw, "group", 1) != c or W.shape[1] != 1 or c % multiple == 0:
            continue
        after = uses.get(dw.output[0], [])
        if len(after) != 1 or after[0].op_type not in _ELEMENTWISE or len(uses.get(after[0].output[0], [])) != 1:
            continue
        pw = uses[after[0].output[0]][0]
        if pw.op_type != "Conv" or attr(pw, "group", 1) != 1 or pw.input[1] not in inits \
                or len(uses.get(pw.input[1], [])) != 1:
            continue
        extra = -c % multiple
        pads_name, padded_in = f"{dw.name or dw.output[0]}_channel_pads", f"{dw.input[0]}_padded_{c + extra}"
        graph.initializer.append(numpy_helper.from_array(np.array([0, 0, 0, 0, 0, extra, 0, 0], np.int64), pads_name))
        graph.node.insert(list(graph.node).index(dw), helper.make_node("Pad", [dw.input[0], pads_name], [padded_in],
                                                                       name=f"{dw.name}_channel_pad"))
        dw.input[0] = padded_in
        replace_init(dw.input[1], np.concatenate([W, np.zeros((extra,) + W.shape[1:], W.dtype)]))
        if len(dw.input) > 2:
            b = numpy_helper.to_array(inits[dw.input[2]])
            replace_init(dw.input[2], np.concatenate([b, np.zeros(extra, b.dtype)]))
        for a in dw.attribute:
            if a.name == "group":
                a.i = c + extra
        P = numpy_helper.to_array(inits[pw.input[1]])
        replace_init(pw.input[1], np.concatenate([P, np.zeros((P.shape[0], extra) + P.shape[2:], P.dtype)], axis=1))
        # the exporter's recorded shapes of the two widened tensors are stale: let onnxruntime infer them
        stale = {dw.output[0], after[0].output[0]}
        kept = [v for v in graph.value_info if v.name not in stale]
        del graph.value_info[:]
        graph.value_info.extend(kept)
        padded += 1
    return padded


def fold_same_pads(model, input_name: str, input_shape) -> int:
    """Fold the "SAME" padding of a quantized (QDQ) network into its convolutions, in place on
    the onnx ModelProto `model`; returns how many Pads were folded. The outputs are the same
    to the bit.

    Why: EfficientNet-Lite's TF "SAME" padding exports as a Pad before each strided
    convolution, its amounts computed at run time from the input's shape (Shape, Gather,
    Concat, ... nodes). onnxruntime folds such a Pad into a float convolution, but not into
    a quantized one: each costs a dequantize, a float Pad and a quantize of the whole
    activation (lite0 DetNet: 3.2 against 2.6 ms a crop folded; docs/experiment_log.md, session 47).

    How: the pad amounts are read once by running the graph on zeros of `input_shape` (with
    the batch size doubled too: they must not depend on it) and stored as constants; then each
    constant-zero Pad of the spatial axes between a DequantizeLinear and a QuantizeLinear of
    the same scale and zero point, whose quantized output feeds only convolutions (through
    their DequantizeLinear), is dropped and its amounts added to those convolutions' `pads`
    (a quantized convolution pads with its input's zero point, which is the value 0); nodes
    left without a use are removed."""
    import numpy as np
    from onnx import helper, numpy_helper
    graph = model.graph
    inits = {t.name: t for t in graph.initializer}
    producer = {o: n for n in graph.node for o in n.output}
    attr = _attribute

    def const(name):
        return numpy_helper.to_array(inits[name]) if name in inits else None

    constant_pads = [n for n in graph.node if n.op_type == "Pad" and attr(n, "mode", b"constant") == b"constant"]
    pads = [n for n in constant_pads if len(n.input) > 1 and n.input[1] not in inits]
    if pads:       # the amounts, computed once: extra outputs of a copy of the graph
        probe = type(model)()
        probe.CopyFrom(model)
        probe.graph.output.extend(helper.make_empty_tensor_value_info(p.input[1]) for p in pads)
        session = check_session(probe.SerializeToString())
        names = [p.input[1] for p in pads]
        shape = list(input_shape)
        values = [session.run(names, {input_name: np.zeros([b] + shape[1:], np.float32)})
                  for b in (shape[0], 2 * shape[0])]
        for p, a, b in zip(pads, *values):
            if not np.array_equal(a, b):
                continue                       # depends on the batch: left as it is
            const_name = f"{p.name or p.output[0]}_amounts"
            graph.initializer.append(numpy_helper.from_array(np.asarray(a, np.int64), const_name))
            inits[const_name] = graph.initializer[-1]
            p.input[1] = const_name
    folded = 0
    use = _readers(graph)
    for pad in constant_pads:
        amounts, value = const(pad.input[1]), (const(pad.input[2]) if len(pad.input) > 2 and pad.input[2] else None)
        dq, after = producer.get(pad.input[0]), use.get(pad.output[0], [])
        if amounts is None or len(amounts) != 8 or amounts.min() < 0 or amounts[[0, 1, 4, 5]].any() \
                or (value is not None and np.any(value != 0)) or dq is None or dq.op_type != "DequantizeLinear" \
                or len(after) != 1 or after[0].op_type != "QuantizeLinear":
            continue
        q = after[0]
        same = all(np.array_equal(const(dq.input[k]), const(q.input[k])) and const(dq.input[k]) is not None
                   for k in (1, 2))
        readers = use.get(q.output[0], [])
        convs = [use.get(r.output[0], []) for r in readers]
        if not same or not readers or any(r.op_type != "DequantizeLinear" for r in readers) \
                or any(not c or any(n.op_type != "Conv" or n.input[0] != r.output[0] for n in c)
                       for r, c in zip(readers, convs)):
            continue
        begin, end = [int(v) for v in amounts[2:4]], [int(v) for v in amounts[6:8]]
        for r, c in zip(readers, convs):
            r.input[0] = dq.input[0]           # the quantized tensor before the Pad, same scale and zero point
            for conv in c:
                old = list(attr(conv, "pads", [0, 0, 0, 0]))
                if attr(conv, "auto_pad", b"NOTSET") not in (b"NOTSET", "NOTSET"):
                    raise ValueError(f"{conv.name}: auto_pad and a Pad before it")
                new = [old[0] + begin[0], old[1] + begin[1], old[2] + end[0], old[3] + end[1]]
                kept = [a for a in conv.attribute if a.name != "pads"]
                del conv.attribute[:]
                conv.attribute.extend(kept + [helper.make_attribute("pads", new)])
        folded += 1
        use = _readers(graph)
    # nodes whose outputs nothing reads any more (the Pads, their quantize pairs, the amounts' arithmetic)
    wanted = {o.name for o in graph.output}
    kept = []
    for node in reversed(list(graph.node)):
        if any(o in wanted for o in node.output):
            kept.append(node)
            wanted.update(node.input)
    del graph.node[:]
    graph.node.extend(reversed(kept))
    used = {i for n in graph.node for i in n.input}
    unused = [t for t in graph.initializer if t.name not in used]
    for t in unused:
        graph.initializer.remove(t)
    return folded


def fold_same_pads_file(path, sample=None) -> int:
    """fold_same_pads on the ONNX file `path` (its first input: an image batch of fixed
    channels and side), rewritten in place only if the folded graph answers as the file does,
    to the bit, on `sample` (an input batch; default: two random images); returns how many
    Pads were folded (0: the file is unchanged)."""
    import numpy as np
    import onnx
    path = Path(path)
    model = onnx.load(str(path))
    image = model.graph.input[0]
    shape = [d.dim_value or 1 for d in image.type.tensor_type.shape.dim]
    x = np.asarray(sample, np.float32) if sample is not None else \
        np.random.default_rng(0).random([2] + shape[1:], dtype=np.float32)
    folded = fold_same_pads(model, image.name, [1] + shape[1:])
    if not folded:
        return 0
    before, after = (check_session(m).run(None, {image.name: x}) for m in (path, model.SerializeToString()))
    if not all(np.array_equal(a, b, equal_nan=True) for a, b in zip(before, after)):
        return 0
    onnx.save(model, str(path))
    return folded
