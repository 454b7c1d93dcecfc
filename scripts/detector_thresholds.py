"""Choose the detector's track-keeping thresholds on training-side held-out real data.

    python scripts/detector_thresholds.py [--detnet int8|float32|F.onnx] [--side-detnet int8|none|F.onnx] [--finder models/finder.onnx]
                                          [--compare KEY=VALUE[,KEY=VALUE] ...]

Runs the detector (finder + DetNet tracking, every frame in order) over real clips kept out
of training: the finder's held-out video (train_finder.VAL_VIDEOS; DetNet trained on its
first 85%), the held-out tails of the training videos (real_data.video_split) and howiema
001 sequences L8/R8 (frames in order). The evaluation
splits (temugeb_stereo, howiema 040, ...) are never read: thresholds chosen here are then
only measured there.

Every hand the detector outputs is "true" when its joints' centre lies within half a hand
size of a labelled hand (MediaPipe pseudo-labels on the clips, human labels on howiema),
else "false" (a desk object, a face, the forearm; or a hand MediaPipe missed, such as one
half out of the frame). Prints the presence and mean heatmap peak (`confidence`) of both
kinds with every track kept, then for each (birth_confidence, min_confidence) pair the
labelled hands found and the false hands output, the detector run again with them: on the
clips in order (tracking), and on every 4th frame of them (--stills-every N) as a still
image (the detector reset before each, as `handeval predict` treats a folder of photos: one
birth per hand).
--compare K=V[,K=V] ...: the same table for any HandDetector settings against the defaults
(HandDetector.load's keywords: finder_threshold=0.15,max_hands=1; fallback=F.onnx;
second_look=0.2), with the found hands' median and mean 2D error / hand size
and the share of output hands on a labelled hand whose handedness is the label's.
--per-clip: then the same per clip (tracked), with DetNet crops per frame, evictions and
handedness turns (HandDetector.stats).
--turn K: every frame (and its labels) turned K quarter turns counter-clockwise first: the
same hands seen from a camera above a desk (K=2: hanging down) or held sideways.
--grey: every frame in grey (three equal channels): the same hands seen by a mono camera.
--shrink F: every frame (and its labels) scaled by F < 1 first: the same hands further away.
--noise S: Gaussian noise of S levels added to every frame (fixed seed): a dark room's sensor.
--stills-every N: every Nth frame as a still (default 4; 1 gives 4x the stills and half the
noise of their figures: docs/models_history.md, "How much of a tracked figure is noise").
"""
import argparse
from pathlib import Path

import numpy as np

from handmocap.training import real_data
from handmocap.perception.detector import HandDetector
from handmocap.training.pose_data import SHARED_DATA
from handmocap.training.train_finder import VAL_VIDEOS

HELD_OUT_VIDEO = f"video/{VAL_VIDEOS[0]}.mp4"


def _sides(lab, i):
    """Handedness ("right" / "left", as the hand appears) of frame i's found pseudo-labels."""
    return ["right" if h == 0 else "left" for h in lab["handedness"][i][lab["found"][i]]]


def clips(shared):
    """(name, frames) of held-out clips; frames is a list of (BGR image, labelled uv list,
    their handedness list)."""
    lab = real_data.load_pseudo_labels(shared / HELD_OUT_VIDEO)
    yield "held-out video", [(img[..., ::-1], list(lab["uv"][i][lab["found"][i]]), _sides(lab, i))
                             for i, img in real_data.read_video(shared / HELD_OUT_VIDEO)]
    for rel in real_data.TRAIN_VIDEOS:
        if rel == HELD_OUT_VIDEO:
            continue
        lab = real_data.load_pseudo_labels(shared / rel)
        _, tail = real_data.video_split(len(lab["found"]))
        keep = set(np.flatnonzero(tail))
        yield f"tail {rel.split('/')[-1]}", [(img[..., ::-1], list(lab["uv"][i][lab["found"][i]]), _sides(lab, i))
                                              for i, img in real_data.read_video(shared / rel, keep)]
    seqs = {}
    for s in real_data.load_howiema(real_data.HOWIEMA_TRAIN_SUBJECT, shared):
        seq = s["name"].split("/")[1]
        if seq in real_data.HOWIEMA_HELD_OUT:
            seqs.setdefault(seq, []).append((s["image"][..., ::-1].copy(), [s["uv"]], [s["handedness"]]))
    for seq, frames in seqs.items():
        yield f"howiema 001 {seq}", frames


def turned(frames, k):
    """Frames turned k quarter turns counter-clockwise (np.rot90), their labels with them:
    per turn a point (x, y) of a frame W px wide goes to (y, W - 1 - x)."""
    out = []
    for image, labels, sides in frames:
        for _ in range(k % 4):
            w = image.shape[1]
            labels = [np.stack([uv[:, 1], w - 1 - uv[:, 0]], 1) for uv in labels]
            image = np.rot90(image)
        out.append((np.ascontiguousarray(image), labels, sides))
    return out


def shrunk(frames, f):
    """Frames scaled by f (INTER_AREA), their labels with them (pixel centres: u' = (u + 0.5) f - 0.5)."""
    import cv2
    out = []
    for image, labels, sides in frames:
        h, w = image.shape[:2]
        small = cv2.resize(image, (round(w * f), round(h * f)), interpolation=cv2.INTER_AREA)
        out.append((small, [(uv + 0.5) * f - 0.5 for uv in labels], sides))
    return out


def noisy(frames, sigma, rng):
    """Frames with Gaussian noise of `sigma` levels added (uint8, clipped), labels as they are."""
    return [(np.clip(image + rng.normal(0, sigma, image.shape), 0, 255).astype(np.uint8), labels, sides)
            for image, labels, sides in frames]


def labels_near(centre, labels):
    """Indices of the labelled hands (each (21,2) px) whose joint centre lies within half
    their joint-box side of `centre` (2,): the hands an output centred there counts as."""
    return [k for k, uv in enumerate(labels)
            if np.linalg.norm(centre - uv.mean(0)) < 0.5 * np.max(uv.max(0) - uv.min(0))]


def score_hands(detector, frames, stills=False):
    """(presence, confidence, is_true, 2D error, handedness right) per output hand (the
    error: mean joint distance / the label's joint-box side; right: 1 or 0 against the
    label's handedness; both NaN for a false hand), and the labelled hands found.
    stills: every frame on its own (the detector reset before each)."""
    detector.reset()
    rows, found, labelled = [], 0, 0
    for image, labels, sides in frames:
        if stills:
            detector.reset()
        hands = detector.process(np.ascontiguousarray(image))
        labelled += len(labels)
        hit = set()
        for h in hands:
            near = labels_near(h["uv"].mean(0), labels)
            uv = labels[near[0]] if near else None
            error = np.nan if uv is None else float(np.mean(np.linalg.norm(h["uv"] - uv, axis=1))
                                                    / np.max(uv.max(0) - uv.min(0)))
            right = np.nan if uv is None else float(h["handedness"] == sides[near[0]])
            rows.append((h["score"], float(np.mean(h["confidence"])), bool(near), error, right))
            hit.update(near)
        found += len(hit)
    return rows, found, labelled


SETTINGS = ((0.0, 0.0), (0.0, 0.1), (0.0, 0.15), (0.0, 0.2), (0.2, 0.15), (0.3, 0.1), (0.3, 0.15))


def parse_setting(text):
    """'second_look=0.2,finder_threshold=0.15' -> {"second_look": 0.2, "finder_threshold": 0.15}."""
    import yaml
    return {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in text.split(","))}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--detnet", default=None)
    ap.add_argument("--side-detnet", default=None,
                    help="the DetNet whose handedness head gives the side (as handeval's --side-detnet)")
    ap.add_argument("--finder", default=None)
    ap.add_argument("--shared", type=Path, default=SHARED_DATA)
    ap.add_argument("--compare", nargs="*", metavar="KEY=VALUE[,KEY=VALUE]",
                    help="instead of the threshold table: these HandDetector settings (e.g. second_look=0.2, "
                         "fallback=F.onnx) against the defaults, with the found hands' 2D error")
    ap.add_argument("--per-clip", action="store_true",
                    help="then, per setting, each clip (tracked in order): hands found, false hands, handedness "
                         "right, DetNet crops per frame, evictions and handedness turns")
    ap.add_argument("--turn", type=int, default=0, metavar="K",
                    help="turn every frame and its labels K quarter turns counter-clockwise first")
    ap.add_argument("--grey", action="store_true", help="every frame in grey (a mono camera)")
    ap.add_argument("--shrink", type=float, default=None, metavar="F",
                    help="scale every frame and its labels by F first (the hands further away)")
    ap.add_argument("--noise", type=float, default=None, metavar="S",
                    help="add Gaussian noise of S levels to every frame (a dark room's sensor)")
    ap.add_argument("--stills-every", type=int, default=4, metavar="N", help="every Nth frame as a still (default 4)")
    args = ap.parse_args()
    data = [(name, turned(frames, args.turn)) for name, frames in clips(args.shared)]
    if args.shrink:
        data = [(name, shrunk(frames, args.shrink)) for name, frames in data]
    if args.noise:
        rng = np.random.default_rng(0)
        data = [(name, noisy(frames, args.noise, rng)) for name, frames in data]
    if args.grey:
        from handmocap.perception.hand_finder import greyed
        data = [(name, [(greyed(image), labels, sides) for image, labels, sides in frames]) for name, frames in data]
    if args.compare is not None:    # `--compare` alone: the defaults' row only
        settings = [("defaults", {})] + [(c, parse_setting(c)) for c in args.compare]
        print("| setting | clips: labelled hands found | false hands | stills: labelled hands found "
              "| false hands | 2D error / hand size, median / mean (clips; stills) | handedness right (clips; stills) |")
        print("|---|---|---|---|---|---|---|")
    else:
        settings = [(f"{b:.2f} | {k:.2f}", dict(birth_confidence=b, min_confidence=k)) for b, k in SETTINGS]
        print("| birth_confidence | min_confidence | clips: labelled hands found | false hands | stills: labelled hands found | false hands |")
        print("|---|---|---|---|---|---|")
    quantiles, clip_rows = [], []
    for label, setting in settings:
        detector = HandDetector.load(args.detnet, args.finder, side_detnet=args.side_detnet, **setting)
        cells, errors, sides = [], [], []
        for stills in (False, True):
            rows, found, labelled = [], 0, 0
            start = dict(detector.stats)
            for name, frames in data:
                before = dict(detector.stats)
                r, f, n = score_hands(detector, frames[::args.stills_every] if stills else frames, stills)
                rows += r
                found, labelled = found + f, labelled + n
                if not stills:
                    spent = {k: detector.stats[k] - before[k] for k in ("crops", "evictions", "handedness_turns")}
                    right = [row[4] for row in r if not np.isnan(row[4])]
                    clip_rows.append(f"| {label} | {name} | {f}/{n} | {sum(not row[2] for row in r)} | "
                                     f"{f'{np.mean(right):.1%}' if right else '–'} | "
                                     f"{spent['crops'] / len(frames):.3f} | {spent['evictions']} | "
                                     f"{spent['handedness_turns']} |")
            if not stills:
                spent = {k: detector.stats[k] - start[k] for k in ("crops", "evictions", "handedness_turns")}
                clip_rows.append(f"| {label} | all clips | {found}/{labelled} | {sum(not row[2] for row in rows)} | "
                                 f"{np.nanmean([row[4] for row in rows]):.1%} | "
                                 f"{spent['crops'] / sum(len(frames) for _, frames in data):.3f} | "
                                 f"{spent['evictions']} | {spent['handedness_turns']} |")
            cells += [f"{found}/{labelled} ({found / labelled:.1%})", str(sum(not row[2] for row in rows))]
            e = [row[3] for row in rows if not np.isnan(row[3])]
            errors.append(f"{np.median(e):.4f} / {np.mean(e):.4f} (n {len(e)})")   # the mean feels wrong sides
            right = [row[4] for row in rows if not np.isnan(row[4])]
            sides.append(f"{np.mean(right):.1%}")
            if args.compare is None and setting["birth_confidence"] == setting["min_confidence"] == 0.0 and not stills:
                r = np.array(rows, float)
                true = r[:, 2] > 0
                quantiles = [f"{kind} hands ({m.sum()}): presence q10/50/90 {np.quantile(r[m, 0], [.1, .5, .9]).round(3)}, "
                             f"confidence q01/10/50/90 {np.quantile(r[m, 1], [.01, .1, .5, .9]).round(3)}"
                             for kind, m in (("true", true), ("false", ~true)) if m.any()]
        if args.compare is not None:
            cells += ["; ".join(errors), "; ".join(sides)]
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)
    if quantiles:
        print("\nwith every track kept: " + "; ".join(quantiles))
    if args.per_clip:
        print("\n| setting | clip (tracked) | labelled hands found | false hands | handedness right "
              "| DetNet crops / frame | evictions | handedness turns |\n|---|---|---|---|---|---|---|---|")
        print("\n".join(clip_rows))

if __name__ == "__main__":
    main()
