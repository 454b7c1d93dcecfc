"""handsynth: the synthetic hand image engine on the command line.

    handsynth sheet -n 64 -o SHEET.png [--procedural] [--frames] [--seed S]
    handsynth generate -n N -o DIR [--workers W] [--shard-size K] [--frames] [--seed S]
    handsynth bench [-n N] [--workers W]            # last line: "<rate> crops/s"
    handsynth backgrounds [--rebuild]               # cut real background crops into the cache
"""
import argparse
import os
import sys
import tempfile
import time

import cv2
import numpy as np

from handmocap.perception.overlay import bone_colour
from handmocap.perception.skeleton import BONES
from .engine import SynthConfig, SynthEngine



def draw_labels(image_rgb, uv, visible, box=None, scale=2, handedness=None):
    """BGR picture (scale x size) of one sample with its skeleton: bones coloured per
    finger, joints filled where visible, hollow where hidden; the hand box in white."""
    h, w = image_rgb.shape[:2]
    img = cv2.resize(image_rgb[..., ::-1], (w * scale, h * scale), interpolation=cv2.INTER_LINEAR)
    pts = uv * scale + (scale - 1) / 2.0
    shift = 4
    p = lambda j: (int(round(pts[j, 0] * (1 << shift))), int(round(pts[j, 1] * (1 << shift))))
    for parent, child in BONES:
        cv2.line(img, p(parent), p(child), bone_colour(child), 1, cv2.LINE_AA, shift)
    for j in range(len(uv)):
        colour = bone_colour(max(j, 1)) if j else (255, 255, 255)
        cv2.circle(img, p(j), 2 << shift, colour, -1 if visible[j] else 1, cv2.LINE_AA, shift)
    if box is not None:
        b = box * scale
        cv2.rectangle(img, (int(b[0]), int(b[1])), (int(b[2]), int(b[3])), (255, 255, 255), 1)
    if handedness is not None:
        cv2.putText(img, "L" if handedness else "R", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                    cv2.LINE_AA)
    return img


def contact_sheet(batch, count, cols=8, scale=1):
    """One BGR image: a grid of `count` samples with their labels drawn."""
    tiles = [draw_labels(batch["image"][i], batch["uv"][i], batch["visible"][i], scale=scale,
                         handedness=batch["handedness"][i]) for i in range(count)]
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[r:r + cols], 1) for r in range(0, len(tiles), cols)]
    return np.concatenate(rows, 0)


def _config(args):
    return SynthConfig(mode="frame" if args.frames else "crop", size=args.size or (256 if args.frames else 128),
                       backgrounds="procedural" if args.procedural else "auto",
                       occluder=args.occluder, second_hand=args.second_hand, touching=args.touching,
                       pitched=args.pitched)


def cmd_sheet(args):
    from .dataset import make_samples
    engine = SynthEngine(_config(args), seed=args.seed)
    batch = make_samples(engine, np.random.default_rng(args.seed), args.n)
    sheet = contact_sheet(batch, args.n, cols=args.cols, scale=args.scale)
    if args.quantize > 1:       # fewer grey levels: a much smaller PNG (for docs/)
        q = args.quantize
        sheet = (sheet // q * q + q // 2).astype(np.uint8)
    cv2.imwrite(args.output, sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {args.output} ({sheet.shape[1]}x{sheet.shape[0]}, {args.n} samples, "
          f"backgrounds: {engine.backgrounds.kind}, poses: {engine.poses.source})")


def cmd_generate(args):
    from .dataset import generate
    meta = generate(args.output, args.n, seed=args.seed, config=_config(args), shard_size=args.shard_size,
                    workers=args.workers, progress=not args.quiet)
    print(f"wrote {meta['n']} samples in {len(meta['shards'])} shards to {args.output} "
          f"({meta['seconds']} s, {meta['rate_per_s']} images/s)")


def cmd_bench(args):
    from .dataset import SynthDataset, generate, make_samples
    config = _config(args)
    rates = {}
    engine = SynthEngine(config, seed=0, log=lambda *a: None)
    make_samples(engine, np.random.default_rng(0), engine.capacity)           # warm-up
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs", flush=True)
    t, cpu = time.perf_counter(), time.process_time()
    make_samples(engine, np.random.default_rng(1), args.n)
    rates["in-process, 1 worker"] = args.n / (time.perf_counter() - t)
    per_cpu_s = args.n / (time.process_time() - cpu)          # all threads of this process (llvmpipe's too)
    print(f"engine, 1 process: {rates['in-process, 1 worker']:.0f} crops/s, {per_cpu_s:.0f} crops per CPU-second "
          f"({args.n} x {config.size} px, backgrounds {engine.backgrounds.kind})", flush=True)
    engine.release()
    best = rates["in-process, 1 worker"]
    with tempfile.TemporaryDirectory() as tmp:
        if args.workers > 1:
            meta = generate(tmp, args.n * args.workers, seed=2, config=config, shard_size=args.n // 2,
                            workers=args.workers, progress=False)
            rate = meta["rate_per_s"]
            print(f"generate to shards, {args.workers} worker processes: {rate:.0f} crops/s "
                  f"(after {meta['startup_seconds']:.1f} s start-up)", flush=True)
            best = max(best, rate)
        else:
            generate(tmp, args.n, seed=2, config=config, shard_size=args.n, workers=1, progress=False)
        ds = SynthDataset(tmp)
        t = time.perf_counter()
        count = sum(len(b["image"]) for b in ds.batches(64, rng=np.random.default_rng(0)))
        print(f"read back from shards: {count / (time.perf_counter() - t):.0f} crops/s", flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}", flush=True)
    print(f"{best:.0f} crops/s")


def cmd_backgrounds(args):
    from .backgrounds import build_real_cache, cache_dir, load_real_backgrounds
    if args.rebuild:
        path = build_real_cache()
        print(f"wrote {path}" if path else "no shared/data/video here: procedural backgrounds only")
        return
    real = load_real_backgrounds()
    print(f"{0 if real is None else len(real)} real background crops in {cache_dir()}")


def main(argv=None):
    ap = argparse.ArgumentParser(prog="handsynth", description="Synthetic labelled hand images.")
    sub = ap.add_subparsers(dest="command", required=True)

    def common(p):
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--frames", action="store_true", help="whole frames (hand finder) instead of crops")
        p.add_argument("--size", type=int, default=None, help="image side in px (128 crops, 256 frames)")
        p.add_argument("--procedural", action="store_true", help="procedural backgrounds only")
        p.add_argument("--occluder", type=float, default=SynthConfig.occluder, help="probability of occluders")
        p.add_argument("--second-hand", type=float, default=SynthConfig.second_hand,
                       help="probability of a second hand")
        p.add_argument("--touching", type=float, default=SynthConfig.touching,
                       help="share of the second hands placed palm to palm with the first (rubbing, clasped)")
        p.add_argument("--pitched", type=float, default=SynthConfig.pitched,
                       help="share of hands pitched 60-88 deg: fingers towards or away from the camera, foreshortened")

    p = sub.add_parser("sheet", help="PNG grid of random samples with their labels")
    p.add_argument("-n", type=int, default=64)
    p.add_argument("-o", "--output", default="synth_sheet.png")
    p.add_argument("--cols", type=int, default=8)
    p.add_argument("--scale", type=int, default=1)
    p.add_argument("--quantize", type=int, default=1, help="colour step (8: a PNG under 1 MB for 64 crops)")
    common(p)
    p.set_defaults(func=cmd_sheet)
    p = sub.add_parser("generate", help="write a data set of N samples as .npz shards")
    p.add_argument("-n", type=int, required=True)
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--shard-size", type=int, default=1024)
    p.add_argument("--quiet", action="store_true")
    common(p)
    p.set_defaults(func=cmd_generate)
    p = sub.add_parser("bench", help="throughput of the engine")
    p.add_argument("-n", type=int, default=1024)
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    common(p)
    p.set_defaults(func=cmd_bench)
    p = sub.add_parser("backgrounds", help="build the real-background cache from shared/data/video")
    p.add_argument("--rebuild", action="store_true")
    p.set_defaults(func=cmd_backgrounds)
    args = ap.parse_args(argv)
    args.func(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
