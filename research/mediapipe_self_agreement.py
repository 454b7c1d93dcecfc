"""How closely MediaPipe agrees with its own labels on the held-back clips: the floor
under `handeval people`'s error figures, whose reference is MediaPipe's pseudo-labels.

    python research/mediapipe_self_agreement.py [--data ../shared/data] [--jitter-seed 0]
                                                [--clips NAME ...] [--work /tmp/mp_self]

For each held-back clip (real_data.WILD_HELD_BACK), its frames are written as PNG twice:
as decoded, and with every pixel moved by a seeded -1, 0 or +1 level (handeval people
--jitter's change, eval_people.frames_of_clip). MediaPipe Hands (tracking mode, model
complexity 1, up to 2 hands: scripts/mediapipe_reference.py --sequence in /tmp/mpenv) reads
both, and its hands are scored against the pack's labels exactly as ours are
(eval_people.score_outputs: found, false hands, median error / hand size, PCK@0.1, side).
"as decoded" checks that the pack's labels were made this way (error near 0); "moved"
is how far MediaPipe itself moves under a change no one can see.
"""
import argparse
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from handmocap.training import eval_people, real_data  # noqa: E402
from handmocap.training.pose_data import SHARED_DATA  # noqa: E402

from handmocap.training.eval_cli import REFERENCE_PYTHON as MP_PYTHON  # noqa: E402  (HANDMOCAP_MEDIAPIPE_PYTHON)


def mediapipe_hands(folder, out):
    """MediaPipe's hands on a folder of consecutive frames -> per frame a list of
    HandKeypoints-like dicts (track_id: the slot, uv (21,2), handedness)."""
    subprocess.run([str(MP_PYTHON), str(ROOT / "scripts" / "mediapipe_reference.py"), "--images", str(folder),
                    "--out", str(out), "--sequence"], check=True, capture_output=True)
    with np.load(out) as d:
        return [[{"track_id": k, "uv": d["all_uv"][i, k].astype(np.float64), "handedness": str(d["all_handedness"][i, k])}
                 for k in range(2) if d["all_found"][i, k]] for i in range(len(d["all_found"]))]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=SHARED_DATA)
    p.add_argument("--jitter-seed", type=int, default=0)
    p.add_argument("--clips", nargs="*", default=None, help="clip stems (default: every held-back clip)")
    p.add_argument("--work", type=Path, default=Path("/tmp/mp_self"))
    args = p.parse_args()
    if not MP_PYTHON.is_file():
        raise SystemExit(f"needs MediaPipe in {MP_PYTHON} (see scripts/mediapipe_reference.py)")
    clips = [v for v in real_data.wild_clips(args.data, held_back=True) if args.clips is None or v.stem in args.clips]
    print("| clip | frames as | MediaPipe's hands | found % | false / frame | median | mean | PCK@0.1 | side % |")
    print("|---|---|---|---|---|---|---|---|---|")
    totals = {}
    for video in clips:
        for kind, seed in (("decoded", None), ("moved", args.jitter_seed)):
            folder = args.work / video.stem / kind
            folder.mkdir(parents=True, exist_ok=True)
            labels = []             # (MediaPipe's hands, reliable, sides) per frame; the frames go to disk
            for i, (bgr, *label) in enumerate(eval_people.frames_of_clip(video, seed)):
                cv2.imwrite(str(folder / f"{i:05d}.png"), bgr)
                labels.append(label)
            hands = mediapipe_hands(folder, args.work / video.stem / f"{kind}.npz")
            s = eval_people.score_outputs((found, *label) for found, label in zip(hands, labels))
            totals.setdefault(kind, []).append(s)
            print(row(video.stem, kind, s), flush=True)
    for kind, runs in totals.items():
        print(row("**all held-back clips**", kind, eval_people.merge(runs)))


def row(name, kind, s):
    m = eval_people.summary(s)
    return (f"| {name} | {kind} | {m['labelled']} | {100 * m['found']:.1f} | {m['false_per_frame']:.3f} | "
            f"{m['median_err']:.3f} | {m['mean_err']:.3f} | {m['pck']:.3f} | {100 * m['side']:.1f} |")


if __name__ == "__main__":
    main()
