"""How many of the data pack's reliable clip hands are foreshortened (wrist -> middle knuckle under
a quarter of the hand's size: the palm at the camera, fingers first), training and held-back
clips of each drop, and the clips that hold most of them (session 52: the view `Kirichovka__want`
shows in 55% of its crops, and DetNet's real training crops almost never).

    python research/foreshortened_share.py [--synth 'runs/detnet_data/synth_train_s35_*']

With --synth, the same share among rendered training crops (`handsynth generate` shards), whose
views are drawn at random (session 52: 2.8% of 24,576).
"""
import argparse

from handmocap.training import real_data


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--synth", default=None, help="rendered shards (a glob), e.g. 'runs/detnet_data/synth_train_s35_*'")
    args = p.parse_args()
    print("| drop | clips | reliable hands | foreshortened | clips holding most |\n|---|---|---|---|---|")
    for drop in real_data.WILD_DROPS:
        for held in (False, True):
            hands, short, per = 0, 0, {}
            for video in real_data.wild_clips(real_data.SHARED_DATA, held_back=held, drops=(drop,)):
                lab = real_data.load_pseudo_labels(video)
                uv = lab["uv"][real_data.reliable_hands(lab)]
                if len(uv):
                    n = int(real_data.foreshortened(uv).sum())
                    hands, short, per[video.stem] = hands + len(uv), short + n, n
            most = ", ".join(f"{k} {v}" for k, v in sorted(per.items(), key=lambda kv: -kv[1])[:2] if v)
            print(f"| {drop} | {'held back' if held else 'training'} | {hands} | {short} ({short / max(hands, 1):.1%}) | {most} |")
    if args.synth:
        from handmocap.training.detnet_data import load_synth, synth_dirs
        synth = load_synth(synth_dirs([args.synth]), 1 << 20)
        if synth is None:
            raise SystemExit(f"no rendered shards match {args.synth}")
        short = real_data.foreshortened(synth["uv"])
        print(f"| rendered | {args.synth} | {len(short)} crops | {short.sum()} ({short.mean():.1%}) | |")


if __name__ == "__main__":
    main()
