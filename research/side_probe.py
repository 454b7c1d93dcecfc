"""How well a linear read of the lite0 trunk's features tells a right hand from a left one, per crop,
against the side heads the detector has: a study for issue 46's side (>= 92% tracked).

    python research/side_probe.py [--trunk imagenet|models/detnet_lite0.pt|W.pt ...] [--side-onnx F ...]

Crops: every real crop of the cache (`detnet_data.load_real`, both drops), cut as the tracker cuts
a tracked hand (joint box x 1.3, turned by the quarter turns that show it upright), unmirrored, and
each also flipped left-right (the other side as it appears). Label: MediaPipe's side.
Features: the trunk's stride-16 map (112 ch, 8x8, mean-pooled to 4x4) and stride-32 map (320 ch,
4x4), flattened (6,912 numbers; the 4x4 layout kept: chirality is where the thumb lies).
The probe: logistic regression (torch, L2, Adam) on the training people's crops; its L2 weight chosen
on the training people's held-out video tails; then read once on the held-back people's crops.
The side heads (`--side-onnx`: exported DetNets, e.g. models/detnet_int8.onnx, the default's side)
read the same crops. Prints per-crop accuracy by group.
"""
import argparse

import numpy as np
import torch

from handmocap.perception.crops import CROP, hand_angle
from handmocap.training import real_data
from handmocap.training.detnet_data import CTX, CTX_CROP_SIDE, HELD_BACK_SOURCE, load_real
from handmocap.training.pose_data import SHARED_DATA


def upright_crops(real):
    """(N,128,128,3) RGB crops of every cached hand, as the tracker cuts them, unmirrored."""
    side, c = CTX_CROP_SIDE, (CTX - 1) / 2
    k = np.round(hand_angle(real["uv"]) / (np.pi / 2)) % 4
    out = np.empty((len(real["uv"]), CROP, CROP, 3), np.uint8)
    for i in range(len(out)):
        # crop_affine's angle is counter-clockwise in the crop; hand_angle clockwise from up
        out[i] = real_data.warp(real["image"][i], real_data.crop_affine(c, c, side, CROP, k[i] * 90.0, False))
    return out


def trunk_features(trunk_name, images, batch=256):
    """(N,6912) float32 features of uint8 RGB crops (N,128,128,3) from the lite0 trunk."""
    import torch.nn.functional as F

    from handmocap.training.efficientnet_lite import LiteTrunk, normalize
    trunk = LiteTrunk()
    if trunk_name == "imagenet":
        trunk.load_imagenet()
    else:
        state = torch.load(trunk_name, weights_only=False, map_location="cpu")
        state = state.get("model", state)
        prefix = "backbone.trunk."
        trunk.load_state_dict({k[len(prefix):]: v.float() for k, v in state.items() if k.startswith(prefix)})
    trunk.eval()
    feats = []
    with torch.no_grad():
        for i in range(0, len(images), batch):
            x = normalize(torch.from_numpy(images[i:i + batch]).permute(0, 3, 1, 2).float() / 255.0)
            _, c16, c32 = trunk(x)
            feats.append(torch.cat([F.avg_pool2d(c16, 2), c32], 1).flatten(1).numpy())
    return np.concatenate(feats)


def fit_probe(x, y, weight_decay, steps=300):
    """Logistic regression on standardised x (N,D), labels y (N,) in {0,1} -> predict(x) -> P(right)."""
    mu, sd = x.mean(0), x.std(0) + 1e-6
    xt, yt = torch.from_numpy((x - mu) / sd), torch.from_numpy(y.astype(np.float32))
    w = torch.zeros(x.shape[1], requires_grad=True)
    b = torch.zeros(1, requires_grad=True)
    opt = torch.optim.Adam([w, b], lr=1e-2)
    for _ in range(steps):
        opt.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(xt @ w + b, yt) + weight_decay * (w * w).sum()
        loss.backward()
        opt.step()
    w, b = w.detach().numpy(), float(b.detach())
    return lambda z: 1.0 / (1.0 + np.exp(-(((z - mu) / sd) @ w + b)))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trunk", nargs="*", default=["imagenet", "models/detnet_lite0.pt"],
                   help="trunks to probe (none: the side heads alone)")
    p.add_argument("--side-onnx", nargs="*", default=["models/detnet_int8.onnx", "models/detnet_lite0_int8.onnx"])
    args = p.parse_args()
    real = load_real(SHARED_DATA, log=lambda *a: None)
    source = real["source"].astype(str)
    held_back = np.char.startswith(source, HELD_BACK_SOURCE)
    photos = np.char.startswith(source, HELD_BACK_SOURCE + "11k/")
    how = np.char.startswith(source, "howiema")
    groups = {"training people (trained on)": ~real["held"].astype(bool),
              "training people's video tails": real["held"].astype(bool) & ~held_back & ~how,
              "howiema 001": how, "held-back people's clips": held_back & ~photos, "held-back photos": photos}
    crops = upright_crops(real)
    right = real["right"].astype(bool)
    # each crop as it is and flipped: the other side as it appears
    images = np.concatenate([crops, crops[:, :, ::-1]])
    label = np.concatenate([right, ~right]).astype(np.float32)
    both = lambda m: np.concatenate([m, m])  # noqa: E731
    print(f"crops: {len(crops)} ({', '.join(f'{k} {m.sum()}' for k, m in groups.items())}), each also flipped")
    rows = {}
    for path in args.side_onnx:
        from handmocap.training.quantize_detnet import OnnxNet
        _, _, p_right = OnnxNet(path).predict(images)
        rows[f"side head of {path}"] = p_right
    for trunk in args.trunk:
        feats = trunk_features(trunk, images)
        train, tails = both(groups["training people (trained on)"]), both(groups["training people's video tails"])
        best = None
        for wd in (1e-4, 1e-3, 1e-2):
            probe = fit_probe(feats[train], label[train], wd)
            acc = float(((probe(feats[tails]) > 0.5) == label[tails]).mean())
            print(f"probe on {trunk}: L2 {wd:g}: training people's tails {acc:.3f}")
            if best is None or acc > best[0]:
                best = (acc, wd, probe)
        rows[f"probe on {trunk} (L2 {best[1]:g})"] = best[2](feats)
    print("\n| per-crop side right | " + " | ".join(groups) + " |")
    print("|---|" + "---|" * len(groups))
    for name, p_right in rows.items():
        cells = [f"{float(((p_right[both(m)] > 0.5) == label[both(m)]).mean()):.3f}" for m in groups.values()]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
