"""Could a small head on lite0 DetNet's own features say which way a hand points in its crop,
better than the keypoints DetNet reads there, and better than reading a new hand's crop at all
four quarter turns (session 52)?

    python research/angle_head_probe.py        # about 7 minutes on 2 cores

Real crops of the data pack (the real-crop caches `handtrain detnet` builds), each turned by a
random angle about its centre, mirrored to a right hand as the detector shows it, at the
detector's scale x 0.9-1.15. The shipped lite0 DetNet (`models/detnet_lite0.pt`, float32, in
eval mode) reads them; its weights are not changed. A two-layer head (features -> 256 -> cos,
sin of the hand's angle, MSE) is fitted on the pooled features of 9,588 training people's
crops (the FPN output pooled 4x4, the stride-32 tap 2x2, the stride-16 tap 4x4: 4,608 values;
`handmocap.training.angle_head`, which grafts such a head onto a DetNet file, fits the same head
on the FPN output alone) and scored on every held-back person's clip crop (both drops, 2,535). The hand's angle is
`crops.hand_angle` of MediaPipe's joints (wrist -> middle knuckle, 0 = upright).

Printed, on the held-back crops:
* the angle error of the head and of DetNet's own keypoints (hand_angle of its 2D read);
* a new hand's turn: with the four quarter turns read and the highest mean heatmap peak kept
  (the detector's way), against one read and the crop turned by the head's angle: the share
  left within 45 degrees of upright (DetNet learnt +-60 about upright);
* per clip, and the share of hands whose wrist -> middle knuckle is under a quarter of the
  hand's size (foreshortened: fingers at the camera), where no angle is well defined; and that
  share among the held-back and the training crops.
"""
from __future__ import annotations

import time

import numpy as np
import torch
import torch.nn.functional as F

from handmocap.perception.crops import angle_apart, hand_angle
from handmocap.training import angle_head, detnet_data, real_data
from handmocap.training.angle_head import turned_crops
from handmocap.training.detnet import DetNet, read_out
from handmocap.training.detnet_init import load_matching

CLIPS = ("Kirichovka", "CoderEnko", "huiwen", "ROSA", "SHREYASH", "piano", "limchaesung", "AlpYksl")


def read(net, images):
    """(features (n,4608), DetNet's keypoint angle (n,), mean heatmap peak (n,)) of crops."""
    feats, angles, peaks, taps = [], [], [], {}
    hooks = [net.backbone.trunk.register_forward_hook(lambda m, i, o: taps.update(trunk=o)),
             net.backbone.register_forward_hook(lambda m, i, o: taps.update(fpn=o))]
    with torch.no_grad():
        for k in range(0, len(images), 128):
            o = net(torch.from_numpy(images[k:k + 128]).permute(0, 3, 1, 2).float() / 255)
            c8, c16, c32 = taps["trunk"]
            feats.append(torch.cat([F.adaptive_avg_pool2d(taps["fpn"], 4).flatten(1), F.adaptive_avg_pool2d(c32, 2).flatten(1),
                                    F.adaptive_avg_pool2d(c16, 4).flatten(1)], 1).numpy())
            angles.append(hand_angle(read_out(o["heatmap"], o["location"], net.stride, "logquad", o["heat_logits"])[0].numpy()))
            peaks.append(o["heatmap"].flatten(2).max(-1).values.mean(1).numpy())
    for h in hooks:
        h.remove()
    return np.concatenate(feats), np.concatenate(angles), np.concatenate(peaks)


def head_angles(weights, features):
    """Angles (radians) the fitted head (angle_head.fit's weights) reads from features (n,d)."""
    W1, b1, W2, b2 = weights
    cos_sin = np.maximum(features @ W1.T + b1, 0.0) @ W2.T + b2
    return np.arctan2(cos_sin[:, 1], cos_sin[:, 0])


def main():
    torch.set_num_threads(2)
    t0 = time.time()
    real = detnet_data.load_real(real_data.SHARED_DATA)
    if real is None:
        raise SystemExit(f"no data pack at {real_data.SHARED_DATA}")
    source = real["source"].astype(str)
    people = np.char.startswith(source, detnet_data.HELD_BACK_SOURCE)
    photos = np.char.startswith(source, detnet_data.HELD_BACK_SOURCE + "11k/")
    test = np.flatnonzero(people & ~photos)
    train = np.random.default_rng(0).permutation(np.flatnonzero(~real["held"] & ~people))[:12000]
    net = DetNet("lite0")
    state = torch.load("models/detnet_lite0.pt", weights_only=False)["model"]
    load_matching(net, {k: v.float() for k, v in state.items()})
    net.eval()

    images, train_angle = turned_crops(real, train, np.random.default_rng(1))
    train_feats = read(net, images)[0]
    images, angle = turned_crops(real, test, np.random.default_rng(2), turns=4)     # (n,4): +0, +90, ... degrees
    feats, keypoint_angle, peaks = read(net, images)
    feats, keypoint_angle, peaks = feats[::4], keypoint_angle[::4], peaks.reshape(-1, 4)
    head_angle = head_angles(angle_head.fit(train_feats, train_angle[:, 0]), feats)
    print(f"{len(train)} training crops, {len(test)} held-back crops, {time.time() - t0:.0f} s")

    truth = angle[:, 0]
    err_head, err_kp = angle_apart(head_angle, truth), angle_apart(keypoint_angle, truth)
    peak_turn = peaks.argmax(1)
    upright_peak = angle_apart(angle[np.arange(len(angle)), peak_turn], 0.0) <= np.pi / 4
    upright_head = err_head <= np.pi / 4        # the crop turned by the head's angle is off by its error
    short = real_data.foreshortened(real["uv"][test])
    print(f"foreshortened hands: {short.mean():.1%} of the held-back crops, "
          f"{real_data.foreshortened(real['uv'][train]).mean():.1%} of the {len(train)} training crops")
    print(f"angle error, median: head {np.degrees(np.median(err_head)):.1f} deg, DetNet's keypoints "
          f"{np.degrees(np.median(err_kp)):.1f}; over 45 deg: head {np.mean(err_head > np.pi / 4):.1%}, "
          f"keypoints {np.mean(err_kp > np.pi / 4):.1%}")
    print(f"a new hand's crop within 45 deg of upright: highest peak of 4 turns {upright_peak.mean():.1%}, "
          f"one read turned by the head {upright_head.mean():.1%}")
    print("| clip | crops | wrist -> middle knuckle < 1/4 hand size | over 45 deg: head | keypoints | "
          "upright: peak of 4 | head |")
    print("|---|---|---|---|---|---|---|")
    for name in CLIPS:
        m = np.char.find(source[test], name) >= 0
        if m.any():
            print(f"| {name} | {m.sum()} | {short[m].mean():.0%} | {np.mean(err_head[m] > np.pi / 4):.1%} | "
                  f"{np.mean(err_kp[m] > np.pi / 4):.1%} | {upright_peak[m].mean():.1%} | {upright_head[m].mean():.1%} |")
    print(f"without the foreshortened hands ({(~short).sum()}): over 45 deg head {np.mean(err_head[~short] > np.pi / 4):.1%}, "
          f"keypoints {np.mean(err_kp[~short] > np.pi / 4):.1%}; upright peak of 4 {upright_peak[~short].mean():.1%}, "
          f"head {upright_head[~short].mean():.1%}")


if __name__ == "__main__":
    main()
