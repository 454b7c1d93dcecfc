"""Writing synthetic data sets to sharded files, reading them back, and streaming.

A data set directory holds `shard_00000.npz`, ... (np.savez, uncompressed: loading is a
memory copy) with the arrays of SynthEngine.batch for `shard_size` samples each, and
`meta.json` (config, seed, sample and shard counts, schema). Shard k is generated from
np.random.default_rng([seed, k]) alone, so a data set is reproducible from its seed,
whatever the number of worker processes, and shards can be generated in any order.

Workers are separate processes, each with its own OpenGL context (llvmpipe renders on
the CPU, one thread per worker); see README.md for measured rates of writing, reading
back and streaming.
"""
import itertools
import json
import multiprocessing as mp
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .engine import SynthConfig, SynthEngine

FORMAT_VERSION = 1


class Progress:
    """tqdm when installed, else a one-line text bar on stderr."""

    def __init__(self, total, unit="img", desc="", enabled=True):
        self.total, self.unit, self.desc, self.enabled, self.count = total, unit, desc, enabled, 0
        self.start = time.time()
        self.bar = None
        if enabled:
            try:
                from tqdm import tqdm
                self.bar = tqdm(total=total, unit=unit, desc=desc)
            except ImportError:
                pass

    def update(self, k):
        self.count += k
        if self.bar is not None:
            self.bar.update(k)
        elif self.enabled:
            frac = self.count / max(self.total, 1)
            rate = self.count / max(time.time() - self.start, 1e-9)
            sys.stderr.write(f"\r{self.desc} [{'#' * int(30 * frac):<30}] {self.count}/{self.total} "
                             f"{rate:.0f} {self.unit}/s")
            sys.stderr.flush()

    def close(self):
        if self.bar is not None:
            self.bar.close()
        elif self.enabled:
            sys.stderr.write("\n")


# ------------------------------------------------------------------ workers
_ENGINE = None


def _init_worker(config, engine_seed, threads, ready=None):
    global _ENGINE
    if threads:
        os.environ["LP_NUM_THREADS"] = str(threads)       # before the GL context exists
    _ENGINE = SynthEngine(config, seed=engine_seed, log=lambda *a: None)
    if ready is not None:
        ready.wait()                                      # tell the parent this worker can start


def make_samples(engine, rng, count):
    """dict of arrays with `count` samples, in atlas-sized batches."""
    parts = []
    left = count
    while left > 0:
        k = min(left, engine.capacity)
        parts.append(engine.batch(rng, k))
        left -= k
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def _shard_job(args):
    seed, index, count, path = args
    samples = make_samples(_ENGINE, np.random.default_rng([seed, index]), count)
    if path is None:
        return samples
    tmp = Path(str(path) + ".tmp.npz")
    np.savez(tmp, **samples)
    tmp.replace(path)
    return count


def _pool(config, engine_seed, workers, wait_ready=False):
    """A pool of `workers` processes with one engine each (llvmpipe: 1 thread each).
    wait_ready: return only once every worker has built its engine (start-up excluded
    from timings)."""
    ctx = mp.get_context("spawn")
    threads = 1 if workers > 1 else 0
    ready = ctx.Barrier(workers + 1) if wait_ready else None
    pool = ctx.Pool(workers, initializer=_init_worker, initargs=(config, engine_seed, threads, ready))
    if ready is not None:
        ready.wait()
    return pool


def generate(out_dir, n, seed=0, config=None, shard_size=1024, workers=1, progress=True):
    """Write n samples into out_dir as shards; returns the meta dict."""
    config = config or SynthConfig()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    counts = [min(shard_size, n - s) for s in range(0, n, shard_size)]
    jobs = [(seed, k, c, out_dir / f"shard_{k:05d}.npz") for k, c in enumerate(counts)]
    launch = time.time()
    if workers > 1:
        with _pool(config, seed, workers, wait_ready=True) as pool:
            bar = Progress(n, desc="handsynth generate", enabled=progress)
            start = time.time()
            for done in pool.imap_unordered(_shard_job, jobs):
                bar.update(done)
            elapsed = time.time() - start
    else:
        _init_worker(config, seed, 0)
        bar = Progress(n, desc="handsynth generate", enabled=progress)
        start = time.time()
        for job in jobs:
            bar.update(_shard_job(job))
        elapsed = time.time() - start
    bar.close()
    startup = start - launch
    meta = {
        "format": FORMAT_VERSION, "n": n, "seed": seed, "shard_size": shard_size,
        "shards": [job[3].name for job in jobs], "counts": counts, "config": asdict(config),
        "backgrounds": _ENGINE.backgrounds.kind if _ENGINE is not None else "see workers",
        "pose_source": _ENGINE.poses.source if _ENGINE is not None else "see workers",
        "seconds": round(elapsed, 2), "startup_seconds": round(startup, 2),
        "rate_per_s": round(n / max(elapsed, 1e-9), 1),
        "schema": "see handmocap/training/synth/engine.py (module docstring)",
    }
    (out_dir / "meta.json").write_text(json.dumps(meta, indent=1))
    return meta


def stream(config=None, seed=0, workers=1, chunk=256):
    """Endless on-the-fly batches (dicts of arrays, `chunk` samples each), for training
    without files. Chunk k comes from np.random.default_rng([seed, k])."""
    config = config or SynthConfig()
    if workers > 1:
        with _pool(config, seed, workers) as pool:
            yield from pool.imap(_shard_job, ((seed, k, chunk, None) for k in itertools.count()))
    else:
        _init_worker(config, seed, 0)
        k = 0
        while True:
            yield _shard_job((seed, k, chunk, None))
            k += 1


class SynthDataset:
    """Random access and batches over a directory written by `generate`.

    >>> ds = SynthDataset("data/synth")
    >>> sample = ds[17]                      # dict of arrays for one image
    >>> for batch in ds.batches(64, rng=np.random.default_rng(0)): ...
    """

    def __init__(self, root):
        self.root = Path(root)
        self.meta = json.loads((self.root / "meta.json").read_text())
        self.counts = np.array(self.meta["counts"])
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])
        self._cache = (None, None)

    def __len__(self):
        return int(self.offsets[-1])

    def shard(self, k):
        """dict of arrays of shard k (the last one read is kept)."""
        if self._cache[0] != k:
            with np.load(self.root / self.meta["shards"][k]) as data:
                self._cache = (k, {key: data[key] for key in data.files})
        return self._cache[1]

    def __getitem__(self, i):
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        i %= len(self)
        k = int(np.searchsorted(self.offsets, i, side="right") - 1)
        return {key: value[i - self.offsets[k]] for key, value in self.shard(k).items()}

    def batches(self, batch_size, rng=None, drop_last=False):
        """Batches (dicts of arrays) over the whole set, shards and samples in random
        order when rng is given (shuffled within a shard: one shard in memory at a time)."""
        order = np.arange(len(self.counts)) if rng is None else rng.permutation(len(self.counts))
        carry = None
        for k in order:
            data = self.shard(int(k))
            idx = np.arange(self.counts[k]) if rng is None else rng.permutation(self.counts[k])
            data = {key: value[idx] for key, value in data.items()}
            if carry is not None:
                data = {key: np.concatenate([carry[key], data[key]]) for key in data}
            count = len(data["image"])
            full = count - count % batch_size
            for s in range(0, full, batch_size):
                yield {key: value[s:s + batch_size] for key, value in data.items()}
            carry = {key: value[full:] for key, value in data.items()} if full < count else None
        if carry is not None and not drop_last:
            yield carry
