"""DetNet on onnxruntime: which file runs (the bundled ones by name), and the runner that reads
a batch of crops, optionally with a second network's handedness head (the default pair)."""
from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from handmocap.perception.crops import CROP
from handmocap.perception.hand_finder import to_input_tensor
from handmocap.perception.onnx_models import (cores, keep_on_helper_cpu, made_from_another, open_session,
                                              stale_quantization)

DETNET_FLOAT32 = Path(__file__).resolve().parents[2] / "models" / "detnet.onnx"   # `handtrain detnet` writes it
DETNET_INT8 = DETNET_FLOAT32.with_name("detnet_int8.onnx")     # `python -m handmocap.training.quantize_detnet` makes it
# lite0: DetNet on EfficientNet-Lite0 from ImageNet weights (session 35), int8: closer keypoints on
# strangers than the int8 (fast-deep) network, a worse side of its own (models/README.md)
DETNET_LITE0 = DETNET_FLOAT32.with_name("detnet_lite0_int8.onnx")
# what runs by default (since session 37): lite0's keypoints, and the side from the int8
# network's handedness head (`side_every` frames apart): tracked on the held-back people's clips,
# side 87.7% against lite0's own 70.6% and int8's 82.9% (docs/experiment_log.md, "Session 37")
DETNET_PATH, DETNET_SIDE_PATH = DETNET_LITE0, DETNET_INT8
DETNET_OUTPUTS = ("uv", "xyz", "confidence", "presence", "handedness")   # what every DetNet file gives
DETNET_NAMES = {"int8": DETNET_INT8, "float32": DETNET_FLOAT32, "lite0": DETNET_LITE0}  # short names: detnet param
# DetNet fine-tuned on grey crops (`handtrain detnet --grey 1`), its int8 copy: run on grey frames
DETNET_GREY = DETNET_FLOAT32.with_name("detnet_grey_int8.onnx")
# crops per onnxruntime run: its memory arena keeps the largest run's activations for good (a
# 14-crop read, a new hand's turns, held lite0 65 MB more than 2-crop reads; benchmarks/bench_memory.py),
# and a CPU reads a crop no faster in a larger batch
MAX_BATCH = 2
# crops whose network input (float32, N x 196 kB) is written into a buffer kept between calls: a
# fresh array of two crops or more costs several times the conversion itself in page faults
# (2 crops: 272 against 33 us); reads of more crops (a new hand's turns, rare) take a fresh one
INPUT_BUFFER_CROPS = 4
# what a crop's side read costs against its keypoint read, for splitting a call's reads between
# the runner's two threads (split_reads): the default pair's side part reads two crops in 1.6 ms,
# lite0 one in 2.6 (benchmarks/bench_detnet.py, session 47); a wrong guess costs time, not outputs
SIDE_CROP_COST = 0.3


def run_in_batches(session, names, x):
    """session.run(names) over crops x (N,3,S,S) float32, MAX_BATCH at a time: its outputs, concatenated."""
    parts = [session.run(names, {"image": x[k:k + MAX_BATCH]}) for k in range(0, len(x), MAX_BATCH)]
    return parts[0] if len(parts) == 1 else [np.concatenate(p) for p in zip(*parts)]


def detnet_path(path=None) -> Path:
    """DetNet file: None -> DETNET_PATH (lite0); "int8" / "float32" / "lite0" -> the bundled files; else a path."""
    return DETNET_PATH if path is None else DETNET_NAMES.get(str(path), Path(path))


def head_only_path(path) -> Path:
    """Where the part of the DetNet file `path` that its handedness head needs is kept:
    `<stem>_side.onnx` beside it (made by `python -m handmocap.training.quantize_detnet
    --side-only PATH`)."""
    path = Path(path)
    return path.with_name(f"{path.stem}_side.onnx")


class SideNetwork:
    """The DetNet whose handedness head gives a pair's side (DetNetRunner `side`): `session`
    answers `handedness` (N,) for crops `image` (N,3,S,S). Where the file's head-only part
    (head_only_path) lies beside it, made from this very file, that part runs: the same
    numbers to the bit, without the heatmap, delta and location heads the side does not read
    (the int8 network: 1.6 against 2.8 ms for two crops; docs/experiment_log.md, session 47).
    `path`: the whole network's file; `file`: the one that runs."""

    def __init__(self, session, path, file=None):
        self.session, self.path, self.file = session, path, file or path

    @classmethod
    def load(cls, path, threads=1):
        path = detnet_path(path)
        head = head_only_path(path)
        if head.is_file():
            session = open_session(head, "DetNet's handedness head", "python -m handmocap.training.quantize_detnet "
                                   f"--side-only {path}", threads)
            if made_from_another(session, head) is None:
                return cls(session, path, head)
            warnings.warn(f"{head} was made from another {path.name} than the one beside it: the whole network reads "
                          f"the side (make the part again with `python -m handmocap.training.quantize_detnet "
                          f"--side-only {path}`)", stacklevel=2)
        runner = DetNetRunner.load(path, threads)       # checks the file and says what is wrong with it
        return cls(runner.session, path)


class DetNetRunner:
    """DetNet on onnxruntime (by default models/detnet_lite0_int8.onnx with the side from
    models/detnet_int8.onnx): (N,128,128,3) uint8 RGB crops -> dict of arrays
    uv (N,21,2) crop px, xyz (N,21,3), confidence (N,21), presence (N,), handedness (N,),
    uv_peak (N,21,2) crop px: the joints the detector tracks with (the heatmap peaks; files
    exported before session 17 have none, and the detector then follows uv).
    side: a SideNetwork, another DetNet whose handedness head answers instead of this one's
    (on the same crops): one network's keypoints with another's side. Called with read_side=False,
    such a pair skips the side network and gives handedness NaN (no reading); a single
    network always reads its own head, which costs nothing more.
    beside: a second thread reads beside the caller's (onnxruntime lets go of the GIL): the
    crops' keypoint and side reads are split between the two threads so that each has about
    half the work (split_reads). A frame then costs about the longer of the two, not their
    sum, where a second core is free (a crop costs the same read alone or in a batch on a
    CPU); the outputs are the same. Default: where the machine has more than one core."""

    def __init__(self, session, side=None, path=None, beside=None):
        self.session, self.side, self.path = session, side, path     # path: the file, where loaded from one
        self.beside = cores() > 1 if beside is None else beside
        self._pool = None               # the second thread, made on first use
        self.pin_helper = True          # that thread kept on onnx_models.cpu_split's helper CPU
        self._input = None              # the network input buffer (network_input), made on first use
        self.outputs = [o.name for o in session.get_outputs()]
        missing = [o for o in DETNET_OUTPUTS if o not in self.outputs]
        if missing:    # another network's file (a finder, IKNet): one clear error, not a KeyError per frame
            raise ValueError(f"{path or 'this model'} is not a DetNet: its outputs are {', '.join(self.outputs)}, "
                             f"not {', '.join(DETNET_OUTPUTS)} (`handtrain detnet` makes one)")
        # px: the crop side the file was exported for (its input's fixed side), else CROP
        side_px = session.get_inputs()[0].shape[-1]
        self.crop_side = side_px if isinstance(side_px, int) else CROP

    @classmethod
    def load(cls, path=None, threads=1, side_path=None):
        """path: None (the default: models/detnet_lite0_int8.onnx, its side from
        models/detnet_int8.onnx unless side_path says otherwise), "int8"
        (models/detnet_int8.onnx), "float32" (models/detnet.onnx), "lite0" or a file;
        side_path: the DetNet whose handedness head gives the side (None: the default pair's
        for path None, else this one's; "none": this one's). Warns when an int8 file was made
        from another float32 network than the one beside it."""
        if path is None and side_path is None:
            side_path = DETNET_SIDE_PATH
        path = detnet_path(path)
        made_by = "python -m handmocap.training.quantize_detnet" if path == DETNET_INT8 else "handtrain detnet"
        session = open_session(path, "DetNet", made_by, threads)
        stale = stale_quantization(session, path, "python -m handmocap.training.quantize_detnet")
        if stale:
            warnings.warn(stale, stacklevel=2)
        return cls(session, SideNetwork.load(side_path, threads) if side_path not in (None, "none") else None, path)

    def network_input(self, crops_rgb):
        """(N,3,S,S) float32 in [0, 1] from uint8 crops (N,S,S,3), written into a buffer kept
        between calls for up to INPUT_BUFFER_CROPS crops (valid until the next call)."""
        crops = np.asarray(crops_rgb)
        if len(crops) > INPUT_BUFFER_CROPS:
            return to_input_tensor(crops)
        planes = (crops.shape[3], *crops.shape[1:3])                          # (3,S,S)
        if self._input is None or self._input.shape[1:] != planes:
            self._input = np.empty((INPUT_BUFFER_CROPS, *planes), np.float32)
        return to_input_tensor(crops, out=self._input[:len(crops)])

    def __call__(self, crops_rgb, read_side=True, side_only=0):
        """side_only: with a side network, the last this many crops are read by it alone (the
        mirror votes: only their handedness is wanted), so every output but `handedness` has
        that many rows fewer."""
        x = self.network_input(crops_rgb)
        crops = len(x) - side_only if self.side is not None and side_only else len(x)   # read for keypoints
        sides = len(x) if read_side and self.side is not None else 0                   # read for the side
        here_k, here_s = split_reads(crops, sides) if self.beside else (crops, sides)
        there = None
        if here_k < crops or here_s < sides:
            there = self.second_thread().submit(self._read, x[here_k:crops], x[here_s:sides])
        keypoints, side = self._read(x[:here_k], x[:here_s])
        if there is not None:
            more_keypoints, more_side = there.result()
            keypoints, side = _joined(keypoints, more_keypoints), _joined(side, more_side)
        out = dict(zip(self.outputs, keypoints))
        if self.side is not None:
            out["handedness"] = side[0] if sides else np.full(len(x), np.nan, np.float32)
        return out

    def second_thread(self) -> ThreadPoolExecutor:
        """The runner's second thread (`beside`), made on first use: its caller may also give it
        work of its own between calls (the detector cuts half of a frame's crops there)."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="detnet-beside",
                                            initializer=keep_on_helper_cpu if self.pin_helper else None)
        return self._pool

    def _read(self, keypoint_crops, side_crops):
        """One thread's share of a call: (this network's outputs on keypoint_crops, a list of
        arrays in `outputs` order; the side network's [handedness (M,)] on side_crops), each
        None where it has no crops."""
        keypoints = run_in_batches(self.session, None, keypoint_crops) if len(keypoint_crops) else None
        side = run_in_batches(self.side.session, ["handedness"], side_crops) if len(side_crops) else None
        return keypoints, side


def _joined(here, there):
    """The caller's thread's outputs (a list of arrays) then the second thread's, row after row;
    where one of them read no crops (None), the other's as they are (no copy)."""
    if here is None or there is None:
        return there if here is None else here
    return [np.concatenate(p) for p in zip(here, there)]


def split_reads(crops, sides, side_cost=SIDE_CROP_COST):
    """(k, s): a call's first k keypoint reads and first s side reads go on the caller's
    thread, the others on the second one, so that the busier thread has as little as can
    be (a keypoint read costs 1, a side read `side_cost`); of splits as even, the one that
    leaves more on the caller's thread. E.g. two tracked hands on a frame that reads their
    side: a keypoint and a side read on each thread, not both keypoint reads on one."""
    best = None
    for k in range(crops + 1):
        for s in range(sides + 1):
            busier = max(k + side_cost * s, crops - k + side_cost * (sides - s))
            key = (round(busier, 9), -(k + side_cost * s))
            if best is None or key < best[0]:
                best = (key, (k, s))
    return best[1]
