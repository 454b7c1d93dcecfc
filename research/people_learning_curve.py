"""Does DetNet read strangers better with more training people? A learning curve by people.

    python research/people_learning_curve.py --keep all  --run-dir runs/detnet/lc_all  [handtrain detnet options]
    python research/people_learning_curve.py --keep half --run-dir runs/detnet/lc_half [handtrain detnet options]
    python research/people_learning_curve.py --keep none --run-dir runs/detnet/lc_none [handtrain detnet options]

Runs `handtrain detnet` with the real cache's video/wild training crops cut to the clips of
some of their people: `all` keeps every training person's clips, `half` only those of
HALF_OWNERS (6 of the 13 uploaders, 1,230 of the 2,937 crops), `none` none of them. Every
other real crop (webcams, 11K Hands, scenes, howiema 001), the negatives and the held-back
people's crops (validation only) stay as they are. Start the runs from a network that never
saw the wild clips (session 20's, `git show 11aaa76:models/detnet.onnx`), and compare the held-back
people's crops of the runs' exports (`python -m handmocap.training.quantize_detnet --compare`).
"""
import argparse
import sys

import numpy as np

from handmocap.training import train_cli, train_detnet
from handmocap.training.detnet_data import WILD_SOURCE

# uploaders of the video/wild training clips kept by --keep half (about half the crops and people)
HALF_OWNERS = ("Criminal-9527", "rubenwo", "jthawme", "klyct", "DUN-official", "iwilare")


def kept_rows(source, held, keep):
    """(N,) bool: the real cache rows a run keeps; every row but the video/wild training crops
    of the people `keep` drops."""
    source = np.asarray(source).astype(str)
    wild = np.char.startswith(source, WILD_SOURCE) & ~np.asarray(held, bool)
    if keep == "all":
        return np.ones(len(source), bool)
    if keep == "none":
        return ~wild
    owner = np.array([s.split("/", 1)[1].split("__")[0] if w else "" for s, w in zip(source, wild)])
    return ~wild | np.isin(owner, HALF_OWNERS)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--keep", choices=("all", "half", "none"), required=True)
    args, rest = p.parse_known_args()
    full_load = train_detnet.load_real

    def load_some(shared, log=print):
        real = full_load(shared, log)
        if real is None:
            raise SystemExit("this study needs the data pack's real crops")
        real = dict(real)
        rows = kept_rows(real["source"], real["held"], args.keep)
        for k in ("image", "uv", "right", "weight", "held", "source", "xyz", "has_3d"):
            if k in real:
                real[k] = real[k][rows]
        wild = np.char.startswith(real["source"].astype(str), WILD_SOURCE) & ~real["held"]
        print(f"--keep {args.keep}: {int(wild.sum())} video/wild training crops of {len(real['held'])} rows")
        return real

    train_detnet.load_real = load_some
    sys.exit(train_cli.main(["detnet", *rest]))


if __name__ == "__main__":
    main()
