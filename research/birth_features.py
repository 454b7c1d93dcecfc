"""What tells a true track birth from a false one? Features of every birth on the
training-side held-out clips (scripts/detector_thresholds.py's clips; evaluation splits
never read).

    python research/birth_features.py [--detnet F] [--out births.json]

Runs the detector with birth_confidence 0 (every proposed hand is born) over the clips in
order and as stills, and records for each birth: the mean heatmap peak on the finder's
crop (`peak_first`) and on the re-cut crop (`peak`), the presence, the agreement of the
two predictions (`disagreement`: median joint distance / hand size) and whether it lies
on a labelled hand (`true`). Prints, for each feature, how many true births a threshold
keeps at how many false ones.
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "scripts"))   # detector_thresholds, a tool
from detector_thresholds import clips, labels_near  # noqa: E402

from handmocap.perception.detector import HandDetector  # noqa: E402
from handmocap.training.pose_data import SHARED_DATA  # noqa: E402


class RecordingDetector(HandDetector):
    """HandDetector that keeps the features of each new track's first frame in `births`."""

    def _run(self, image, crops):
        out = super()._run(image, crops)
        self.calls.append((list(crops), {k: v.copy() for k, v in out.items()}))   # _track overwrites out in place
        return out

    def _track(self, image, new):
        self.calls, self.births = [], []
        before = list(self.tracks)
        idx = [i for i, t in enumerate(before) if t in new and t.age == 0]   # before _track ages them
        hands = super()._track(image, new)
        if idx and len(self.calls) >= 2:            # call 0: every track's crop; call 1: the new ones re-cut
            (first_crops, first), (crops, again) = self.calls[:2]
            for k, i in enumerate(idx):
                uv0, uv = first_crops[i].to_frame(first["uv"][i]), crops[k].to_frame(again["uv"][k])
                size = max(float(np.max(uv.max(0) - uv.min(0))), 1e-6)
                self.births.append({"peak_first": float(first["confidence"][i].mean()),
                                    "peak": float(again["confidence"][k].mean()),
                                    "presence": float(again["presence"][k]),
                                    "disagreement": float(np.median(np.linalg.norm(uv0 - uv, axis=1)) / size),
                                    "uv": uv})
        return hands


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--detnet", default=None)
    ap.add_argument("--shared", type=Path, default=SHARED_DATA)
    ap.add_argument("--out", type=Path, default=None, help="write every birth's features (JSON)")
    args = ap.parse_args()
    det = RecordingDetector.load(args.detnet, birth_confidence=0.0)
    rows = []
    for name, frames in clips(args.shared):
        for stills in (False, True):
            det.reset()
            for image, labels, _ in (frames[::4] if stills else frames):
                if stills:
                    det.reset()
                det.births = []
                det.process(np.ascontiguousarray(image))
                for b in det.births:
                    true = bool(labels_near(b.pop("uv").mean(0), labels))
                    rows.append({"clip": name, "stills": stills, "true": true, **b})
    if args.out:
        args.out.write_text(json.dumps(rows))
    t = np.array([r["true"] for r in rows])
    print(f"{len(rows)} births, {t.sum()} true, {(~t).sum()} false")
    for key, above in (("peak", True), ("peak_first", True), ("disagreement", False)):
        v = np.array([r[key] for r in rows])
        cells = []
        for th in np.quantile(v[t], [0.02, 0.05, 0.1] if above else [0.98, 0.95, 0.9]) if t.any() else []:
            keep = v >= th if above else v <= th
            cells.append(f"{'>=' if above else '<='} {th:.3f}: true {keep[t].mean():.1%}, false {keep[~t].sum()}")
        print(f"{key}: " + "; ".join(cells))


if __name__ == "__main__":
    main()
