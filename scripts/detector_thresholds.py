"""Choose the detector's track-keeping thresholds on training-side held-out real data.

    python scripts/detector_thresholds.py [--detnet models/detnet.onnx] [--finder models/finder.onnx]
                                          [--candidates | --fallback F.onnx ... | --refine
                                           | --compare KEY=VALUE[,KEY=VALUE] ...]

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
clips in order (tracking), and on every 4th frame of them as a still image (the detector
reset before each, as `handeval predict` treats a folder of photos: one birth per hand).
--candidates: the same table for how many of the finder's boxes DetNet picks new tracks
from (HandDetector's `candidates`) and the finder's threshold, at the default thresholds.
--fallback F.onnx ...: the same for a second finder tried where the first one's boxes gave
no track (HandDetector's `fallback`), each against none. --refine: the same for the DetNet
passes on a new track's re-cut crop, with the found hands' 2D error. --compare K=V[,K=V]
...: any HandDetector settings against the defaults, likewise.
"""
import argparse
from pathlib import Path

import numpy as np

from handmocap import real_data
from handmocap.detector import HandDetector
from handmocap.pose_data import SHARED_DATA
from handmocap.train_finder import VAL_VIDEOS

HELD_OUT_VIDEO = f"video/{VAL_VIDEOS[0]}.mp4"


def clips(shared):
    """(name, frames) of held-out clips; frames is a list of (BGR image, labelled uv list)."""
    lab = real_data.load_pseudo_labels(shared / HELD_OUT_VIDEO)
    yield "held-out video", [(img[..., ::-1], list(lab["uv"][i][lab["found"][i]]))
                             for i, img in real_data.read_video(shared / HELD_OUT_VIDEO)]
    for rel in real_data.TRAIN_VIDEOS:
        if rel == HELD_OUT_VIDEO:
            continue
        lab = real_data.load_pseudo_labels(shared / rel)
        _, tail = real_data.video_split(len(lab["found"]))
        keep = set(np.flatnonzero(tail))
        yield f"tail {rel.split('/')[-1]}", [(img[..., ::-1], list(lab["uv"][i][lab["found"][i]]))
                                              for i, img in real_data.read_video(shared / rel, keep)]
    seqs = {}
    for s in real_data.load_howiema(real_data.HOWIEMA_TRAIN_SUBJECT, shared):
        seq = s["name"].split("/")[1]
        if seq in real_data.HOWIEMA_HELD_OUT:
            seqs.setdefault(seq, []).append((s["image"][..., ::-1].copy(), [s["uv"]]))
    for seq, frames in seqs.items():
        yield f"howiema 001 {seq}", frames


ERRORS = []   # per true output hand: mean 2D joint error / the label's joint-box side (--refine)


def score_hands(detector, frames, stills=False):
    """(presence, confidence, is_true) per output hand, and the labelled hands found.
    stills: every frame on its own (the detector reset before each)."""
    detector.reset()
    rows, found, labelled = [], 0, 0
    for image, labels in frames:
        if stills:
            detector.reset()
        hands = detector.process(np.ascontiguousarray(image))
        labelled += len(labels)
        hit = set()
        for h in hands:
            c = h["uv"].mean(0)
            near = [k for k, uv in enumerate(labels)
                    if np.linalg.norm(c - uv.mean(0)) < 0.5 * np.max(uv.max(0) - uv.min(0))]
            rows.append((h["score"], float(np.mean(h["confidence"])), bool(near)))
            hit.update(near)
            if near:
                uv = labels[near[0]]
                ERRORS.append(float(np.mean(np.linalg.norm(h["uv"] - uv, axis=1)) / np.max(uv.max(0) - uv.min(0))))
        found += len(hit)
    return rows, found, labelled


SETTINGS = ((0.0, 0.0), (0.0, 0.1), (0.0, 0.15), (0.0, 0.2), (0.2, 0.15), (0.3, 0.1), (0.3, 0.15))
# --candidates: (candidates, finder_threshold) at the shipped birth/end thresholds
CANDIDATES = ((0, 0.3), (4, 0.3), (4, 0.15), (6, 0.1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--detnet", default=None)
    ap.add_argument("--finder", default=None)
    ap.add_argument("--shared", type=Path, default=SHARED_DATA)
    ap.add_argument("--fallback", nargs="+", metavar="FINDER.onnx",
                    help="compare a second hand finder tried where the first one's boxes gave no track "
                         "(HandDetector's fallback), each of these against none, at the default thresholds")
    ap.add_argument("--compare", nargs="+", metavar="KEY=VALUE[,KEY=VALUE]",
                    help="compare HandDetector settings (e.g. duplicate_joints=0.3) against the defaults, "
                         "with the found hands' 2D error")
    ap.add_argument("--refine", action="store_true",
                    help="compare DetNet passes on a new track's re-cut crop (HandDetector's refine_passes) by "
                         "hands found and their 2D error, at the default thresholds")
    ap.add_argument("--candidates", action="store_true",
                    help="compare how many finder boxes DetNet chooses from (HandDetector's candidates, "
                         "finder_threshold) at the default birth/end thresholds, instead")
    args = ap.parse_args()
    data = list(clips(args.shared))
    if args.compare:
        import yaml
        settings = [{"setting": "defaults"}] + [
            {"setting": c, **{k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in c.split(","))}}
            for c in args.compare]
        print("| setting | clips: labelled hands found | false hands | stills: labelled hands found "
              "| false hands | 2D error / hand size, median (clips; stills) |")
    elif args.refine:
        settings = [dict(refine_passes=k, candidates=0) for k in (1, 2, 3)]
        print("| refine_passes | candidates | clips: labelled hands found | false hands | stills: labelled hands found "
              "| false hands | 2D error / hand size, median (clips; stills) |")
    elif args.fallback:
        settings = [dict(fallback_path=None, candidates=0)] + [dict(fallback_path=f, candidates=0) for f in args.fallback]
        print("| fallback finder | candidates | clips: labelled hands found | false hands | stills: labelled hands found | false hands |")
    elif args.candidates:
        settings = [dict(candidates=k, finder_threshold=t) for k, t in CANDIDATES]
        print("| candidates | finder_threshold | clips: labelled hands found | false hands | stills: labelled hands found | false hands |")
    else:
        settings = [dict(birth_confidence=b, min_confidence=k) for b, k in SETTINGS]
        print("| birth_confidence | min_confidence | clips: labelled hands found | false hands | stills: labelled hands found | false hands |")
    print("|---|---|---|---|---|" + ("" if args.compare else "---|") + ("---|" if args.refine or args.compare else ""))
    quantiles = []
    for setting in settings:
        birth, keep = setting.get("birth_confidence", 0.3), setting.get("min_confidence", 0.1)
        detector = HandDetector.load(args.detnet, args.finder, **{k: v for k, v in setting.items() if k != "setting"})
        cells, errors = [], []
        for stills in (False, True):
            rows, found, labelled = [], 0, 0
            ERRORS.clear()
            for name, frames in data:
                r, f, n = score_hands(detector, frames[::4] if stills else frames, stills)
                rows += r
                found, labelled = found + f, labelled + n
            cells += [f"{found}/{labelled} ({found / labelled:.1%})", str(sum(not t for *_, t in rows))]
            errors.append(f"{np.median(ERRORS):.4f} (n {len(ERRORS)})")
            if not (args.candidates or args.fallback or args.refine or args.compare) and birth == keep == 0.0 \
                    and not stills:
                r = np.array(rows, float)
                true = r[:, 2] > 0
                quantiles = [f"{kind} hands ({m.sum()}): presence q10/50/90 {np.quantile(r[m, 0], [.1, .5, .9]).round(3)}, "
                             f"confidence q01/10/50/90 {np.quantile(r[m, 1], [.01, .1, .5, .9]).round(3)}"
                             for kind, m in (("true", true), ("false", ~true)) if m.any()]
        if args.compare:
            print(f"| {setting['setting']} | " + " | ".join(cells + ["; ".join(errors)]) + " |", flush=True)
            continue
        first, second = setting.values()
        if args.refine:
            cells.append("; ".join(errors))
        print(f"| {first if isinstance(first, str) or first is None else f'{first:g}'} | {second:g} | "
              + " | ".join(cells) + " |", flush=True)
    if quantiles:
        print("\nwith every track kept: " + "; ".join(quantiles))


if __name__ == "__main__":
    main()
