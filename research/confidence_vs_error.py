"""Does a hand's confidence on `/hand/keypoints` say how far off its joints are, on people the
project never trained on? A robot user would drop the hands (or joints) it flags.

    python research/confidence_vs_error.py [--detnet F] [--jitter-seed S]

Tracks the held-back clips (real_data.WILD_HELD_BACK) and scores them as `handeval people`
does (eval_people.score_frames), keeping for every output hand on a reliable MediaPipe hand
its joint confidences (the heatmap peaks: the message's `confidence`; their mean per hand),
its `score` (presence) and its error (mean joint distance / hand size; per joint too). Prints:
- the hands kept by a confidence threshold: share kept, median error, PCK@0.1, side right;
- the same by score;
- per joint: the joints' error by quartile of their own confidence;
- per clip: the rank correlation within the clip, and the median error of its hands above
  and below the threshold (does the confidence pick out bad frames, or only hard clips?).
"""
import argparse

import numpy as np

from handmocap.training import real_data
from handmocap.training.eval_people import PCK_AT, clip_fps, frames_of_clip, merge, score_frames


def kept_table(name, key, thresholds, joint_err, right):
    """Markdown rows: hands with key (n,) >= each threshold; joint_err (n,21), right (n,) bool."""
    err = joint_err.mean(1)
    out = [f"| {name} ≥ | hands kept % | median | PCK@0.1 | side right % | median of the hands left out |",
           "|---|---|---|---|---|---|"]
    for t in thresholds:
        m = key >= t
        if m.any():
            out.append(f"| {t:.2f} | {100 * m.mean():.1f} | {np.median(err[m]):.3f} | "
                       f"{(joint_err[m] <= PCK_AT).mean():.3f} | {100 * right[m].mean():.1f} | "
                       f"{np.median(err[~m]) if (~m).any() else float('nan'):.3f} |")
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--detnet", default=None, help="a DetNet ONNX file (default: the detector's)")
    p.add_argument("--jitter-seed", type=int, default=None, help="frames moved by -1/0/+1 with this seed")
    p.add_argument("--threshold", type=float, default=0.5, help="mean confidence the per-clip table splits at")
    args = p.parse_args()
    from handmocap.perception.detector import HandDetector
    detector = HandDetector.load(**({"detnet_path": args.detnet} if args.detnet else {}))
    videos = real_data.wild_clips(held_back=True)
    clips = []
    for video in videos:
        clips.append(score_frames(detector, frames_of_clip(video, args.jitter_seed), fps=clip_fps(video)))
        print(f"  {video.stem}: {len(clips[-1]['err'])} hands", flush=True)
    clip_of = np.concatenate([np.full(len(s["err"]), c) for c, s in enumerate(clips)])
    s = merge(clips)
    conf, score, joint_err, err, right = s["confidence"], s["presence"], s["joint_err"], s["err"], s["right_side"]
    mean_conf = conf.mean(1)                        # (n,) a hand's mean joint confidence
    print(f"\nheld-back clips: {len(err)} scored hands; mean confidence quartiles "
          f"{np.round(np.quantile(mean_conf, [0.25, 0.5, 0.75]), 3).tolist()}; "
          f"Spearman (mean confidence, error) {spearman(mean_conf, err):.2f}, "
          f"(score, error) {spearman(score, err):.2f}\n")
    print("\n".join(kept_table("mean confidence", mean_conf, [0.0, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8], joint_err, right)))
    print()
    print("\n".join(kept_table("score", score, np.quantile(score, [0, 0.25, 0.5, 0.75, 0.9]), joint_err, right)))
    edges = np.quantile(conf, [0, 0.25, 0.5, 0.75, 1])
    print("\n| a joint's confidence | joints | median joint error | PCK@0.1 |\n|---|---|---|---|")
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (conf >= lo) & (conf <= hi)
        print(f"| {lo:.2f}–{hi:.2f} | {m.sum()} | {np.median(joint_err[m]):.3f} | {(joint_err[m] <= PCK_AT).mean():.3f} |")
    print(f"\n| clip | hands | Spearman (mean confidence, error) | median error: confidence ≥ {args.threshold} (share) "
          f"| below |\n|---|---|---|---|---|")
    for c, video in enumerate(videos):
        m = clip_of == c
        if m.sum() < 10:
            continue
        hi, lo = m & (mean_conf >= args.threshold), m & (mean_conf < args.threshold)
        med = lambda x: f"{np.median(err[x]):.3f}" if x.any() else "–"  # noqa: E731
        print(f"| {video.stem} | {m.sum()} | {spearman(mean_conf[m], err[m]):.2f} | {med(hi)} "
              f"({hi.sum() / m.sum():.0%}) | {med(lo)} |")


def spearman(a, b):
    """Rank correlation of two (n,) arrays."""
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


if __name__ == "__main__":
    main()
