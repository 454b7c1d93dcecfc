"""How many of the data pack's reliable clip hands are foreshortened (wrist -> middle knuckle under
a quarter of the hand's size: the palm at the camera, fingers first), training and held-back
clips of each drop, and the clips that hold most of them (session 52: the view `Kirichovka__want`
shows in 55% of its crops, and DetNet's real training crops almost never).

    python research/foreshortened_share.py
"""
import numpy as np

from handmocap.training import real_data


def main():
    print("| drop | clips | reliable hands | foreshortened | clips holding most |\n|---|---|---|---|---|")
    for drop in real_data.WILD_DROPS:
        for held in (False, True):
            hands, short, per = 0, 0, {}
            for video in real_data.wild_clips(real_data.SHARED_DATA, held_back=held, drops=(drop,)):
                lab = real_data.load_pseudo_labels(video)
                uv = lab["uv"][real_data.reliable_hands(lab)]
                if len(uv):
                    n = int((np.linalg.norm(uv[:, 9] - uv[:, 0], axis=-1) / real_data.hand_size(uv) < 0.25).sum())
                    hands, short, per[video.stem] = hands + len(uv), short + n, n
            most = ", ".join(f"{k} {v}" for k, v in sorted(per.items(), key=lambda kv: -kv[1])[:2] if v)
            print(f"| {drop} | {'held back' if held else 'training'} | {hands} | {short} ({short / max(hands, 1):.1%}) | {most} |")


if __name__ == "__main__":
    main()
