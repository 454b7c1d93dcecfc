"""MediaPipe Hands as the reference: its predictions in handeval's PRED.npz format.

Run with a throwaway environment that has MediaPipe (never a project dependency):

    python3.11 -m venv /tmp/mpenv
    /tmp/mpenv/bin/pip install mediapipe==0.10.21 opencv-python-headless numpy
    /tmp/mpenv/bin/python scripts/mediapipe_reference.py --images DIR|VIDEO --out MP.npz \
        [--K-file K.npy | --K fx,fy,cx,cy] [--sequence]
    handeval score --pred MP.npz --gt GT.npz          # scored exactly like our predictions
    /tmp/mpenv/bin/python scripts/mediapipe_reference.py --bench VIDEO [--frames 200] [--max-hands 2]   # ms per frame
    /tmp/mpenv/bin/python scripts/mediapipe_reference.py --bench VIDEO --paced 30   # latency per frame at 30 fps

mediapipe.solutions.hands (the legacy Hands solution bundled with the package, model
complexity 1, up to 2 hands, confidences 0.5): static-image mode for a folder of
independent images, tracking (video) mode for a video file or --sequence. Written per
image (numpy + OpenCV only, no handmocap import), best-scoring hand first:
  uv (N,21,2) px; xyz_rel (N,21,3) its world landmarks made root-relative (joint 9) and
  scale-normalized (|0-9| = 1); xyz (N,21,3) the world landmarks (metres, hand-centred)
  placed at a camera-frame root from the hand-size ratio (depth = f * 3D spread / 2D
  spread, the root pixel back-projected): MediaPipe gives no camera-frame position, and
  the 3D scores align root and scale anyway; found (N,); handedness (N,) str; score (N,);
  all_* (N,2,...) every hand. Handedness: solutions.hands labels assume a mirrored
  (selfie) image, so on these unmirrored images its label is swapped back.
"""
import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff"}


def frames(source):
    source = Path(source)
    if source.is_dir():
        for p in sorted(q for q in source.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES):
            yield cv2.imread(str(p), cv2.IMREAD_COLOR)
        return
    cap = cv2.VideoCapture(str(source))
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        yield frame
    cap.release()


def K_rows(args, n, size):
    """(n,3,3) K per image: --K, --K-file, or a 60 degree horizontal field of view."""
    if args.K:
        fx, fy, cx, cy = (float(v) for v in args.K.split(","))
        a = np.array([fx, fy, cx, cy])
    elif args.K_file:
        a = np.load(args.K_file)
    else:
        w, h = size
        f = (w / 2) / np.tan(np.radians(30))
        a = np.array([f, f, (w - 1) / 2, (h - 1) / 2])
    a = np.asarray(a, np.float64)
    if a.shape[-1] == 4:
        fx, fy, cx, cy = np.moveaxis(a, -1, 0)
        z, o = np.zeros_like(fx), np.ones_like(fx)
        a = np.stack([np.stack([fx, z, cx], -1), np.stack([z, fy, cy], -1), np.stack([z, z, o], -1)], -2)
    return np.broadcast_to(a, (n, 3, 3)) if a.ndim == 2 else a


def normalized(xyz):
    rel = xyz - xyz[9]
    return rel / np.linalg.norm(rel[0])


def camera_placed(world, uv, K):
    """World landmarks (21,3) moved to a camera-frame root from the hand-size ratio."""
    f = (K[0, 0] + K[1, 1]) / 2
    spread3 = np.sqrt(np.sum(np.var(world[:, :2], axis=0)))
    spread2 = np.sqrt(np.sum(np.var(uv, axis=0)))
    z = f * spread3 / max(spread2, 1e-6)
    root = np.array([(uv[9, 0] - K[0, 2]) / K[0, 0] * z, (uv[9, 1] - K[1, 2]) / K[1, 1] * z, z])
    return world - world[9] + root


def predict(args):
    import mediapipe as mp
    src = Path(args.images)
    sequence = args.sequence or not src.is_dir()
    images = list(frames(src))
    n = len(images)
    h, w = images[0].shape[:2]
    Ks = K_rows(args, n, (w, h))
    out = {"xyz": np.full((n, 21, 3), np.nan, np.float32), "xyz_rel": np.full((n, 21, 3), np.nan, np.float32),
           "uv": np.full((n, 21, 2), np.nan, np.float32), "found": np.zeros(n, bool),
           "handedness": np.full(n, "", "<U5"), "score": np.zeros(n, np.float32),
           "all_xyz": np.full((n, 2, 21, 3), np.nan, np.float32),
           "all_xyz_rel": np.full((n, 2, 21, 3), np.nan, np.float32),
           "all_uv": np.full((n, 2, 21, 2), np.nan, np.float32), "all_found": np.zeros((n, 2), bool),
           "all_handedness": np.full((n, 2), "", "<U5")}
    with mp.solutions.hands.Hands(static_image_mode=not sequence, max_num_hands=2, model_complexity=1,
                                  min_detection_confidence=0.5, min_tracking_confidence=0.5) as hands:
        for i, frame in enumerate(images):
            fh, fw = frame.shape[:2]
            res = hands.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            if not res.multi_hand_landmarks:
                continue
            found = []
            for lm, world, hd in zip(res.multi_hand_landmarks, res.multi_hand_world_landmarks, res.multi_handedness):
                uv = np.array([(p.x * fw, p.y * fh) for p in lm.landmark])
                xyz_w = np.array([(p.x, p.y, p.z) for p in world.landmark])
                c = hd.classification[0]
                label = {"Left": "right", "Right": "left"}[c.label]     # mirrored-input convention swapped back
                found.append((c.score, uv, xyz_w, label))
            found.sort(key=lambda f: -f[0])
            for k, (score, uv, xyz_w, label) in enumerate(found[:2]):
                out["all_uv"][i, k], out["all_xyz_rel"][i, k] = uv, normalized(xyz_w)
                out["all_xyz"][i, k] = camera_placed(xyz_w, uv, Ks[i])
                out["all_found"][i, k], out["all_handedness"][i, k] = True, label
                if k == 0:
                    out["uv"][i], out["xyz_rel"][i], out["xyz"][i] = uv, normalized(xyz_w), out["all_xyz"][i, 0]
                    out["found"][i], out["handedness"][i], out["score"][i] = True, label, score
    np.savez(args.out, **out)
    print(f"MediaPipe on {src}: {n} images, a hand found in {out['found'].sum()} ({out['found'].mean():.1%})")


def bench(args):
    """Median ms per frame of MediaPipe's tracking (video) mode on a video's frames: one
    warm-up pass, then `--repeat` timed passes pooled (one pass's median wanders by up to
    a third on a shared 2-core machine)."""
    import mediapipe as mp
    images = list(frames(args.bench))[:args.frames]
    times, cpu, found = [], [], []
    with mp.solutions.hands.Hands(static_image_mode=False, max_num_hands=args.max_hands,
                                  model_complexity=1) as hands:
        for frame in images:                 # a warm-up pass: models load
            hands.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        for _ in range(args.repeat):
            for frame in images:
                t, c = time.perf_counter(), time.process_time()  # the BGR -> RGB conversion counts: a camera gives BGR frames
                result = hands.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
                times.append(time.perf_counter() - t)
                cpu.append(time.process_time() - c)
                found.append(len(result.multi_hand_landmarks or []))
    # median_cpu_ms: every thread of the process (above median_ms where MediaPipe's graph works on several cores)
    print(json.dumps({"median_ms": 1e3 * float(np.median(times)), "p90_ms": 1e3 * float(np.percentile(times, 90)),
                      "median_cpu_ms": 1e3 * float(np.median(cpu)),
                      "frames": len(images), "passes": args.repeat, "hands_per_frame": float(np.mean(found)),
                      "max_hands": args.max_hands, "size": list(images[0].shape[1::-1])}))


def bench_paced(args):
    """MediaPipe's tracking mode on a video's frames (decoded first) delivered on a `--paced`
    fps clock, as a camera delivers them: each frame's latency = result - its due time.
    Prints the latencies (ms, JSON), after a first pass that loads the models. With --stream
    each frame is decoded when it is due instead (its decoding then counts in its latency, and
    the process holds one frame, as a camera driver does: benchmarks/bench_memory.py)."""
    import itertools

    import mediapipe as mp
    images = itertools.islice(frames(args.bench), args.frames) if args.stream else list(frames(args.bench))[:args.frames]
    with mp.solutions.hands.Hands(static_image_mode=False, max_num_hands=args.max_hands,
                                  model_complexity=1) as hands:
        for frame in itertools.islice(frames(args.bench), 30):
            hands.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        latencies, found = [], []
        t0 = time.perf_counter() + 0.1
        for i, frame in enumerate(images):
            due = t0 + i / args.paced
            time.sleep(max(0.0, due - time.perf_counter()))
            result = hands.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            latencies.append(1e3 * (time.perf_counter() - due))
            found.append(len(result.multi_hand_landmarks or []))
    print(json.dumps({"latency_ms": latencies, "hands_per_frame": float(np.mean(found)), "max_hands": args.max_hands}))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--images")
    p.add_argument("--out")
    k = p.add_mutually_exclusive_group()
    k.add_argument("--K")
    k.add_argument("--K-file")
    p.add_argument("--sequence", action="store_true", help="a folder's images are consecutive video frames")
    p.add_argument("--bench", help="a video: print MediaPipe's median ms per frame (JSON) instead")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--max-hands", type=int, default=2, help="with --bench: max_num_hands (default %(default)s)")
    p.add_argument("--repeat", type=int, default=1, help="with --bench: timed passes (default %(default)s)")
    p.add_argument("--paced", type=float, help="with --bench: frames on this fps clock; print each one's latency")
    p.add_argument("--stream", action="store_true", help="with --paced: decode each frame when it is due, not all first")
    args = p.parse_args()
    if args.bench and args.paced:
        bench_paced(args)
    elif args.bench:
        bench(args)
    elif args.images and args.out:
        predict(args)
    else:
        p.error("give --images and --out, or --bench VIDEO")


if __name__ == "__main__":
    main()
