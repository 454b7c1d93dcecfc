"""Which way the hand points in a DetNet crop: a small head grafted onto an exported DetNet file.

    python -m handmocap.training.angle_head models/detnet_lite0_int8.onnx --out runs/angle/detnet_lite0_int8.onnx

The file gains one output, `hand_angle` (N,2): (cos, sin) of the hand's angle in the crop as
`crops.hand_angle` measures it (wrist -> middle finger's base, clockwise from the crop's up; 0:
upright). Its length says how sure the head is: fitted by least squares onto unit vectors, it
shrinks where the direction is unclear (a palm seen face-on with the fingers at the camera), and
on held-back crops the angle is more than 45 degrees off on 4.8% of the crops where it is at
least 0.5 long, against 64% of the others (session 52).

Why: the detector turns each crop so the hand appears upright, from the angle of DetNet's own
keypoints, and a new hand is read at all four quarter turns to find it. Those keypoints were
trained on hands near upright and read any crop as one: on held-back crops turned at random
their angle is more than 45 degrees off on 29.9% of crops, the head's on 9.6%
(`python research/angle_head_probe.py`).

How: the network is not changed. Its features at the heads' grid (the tensor the heatmap head
reads beside its coordinate channels: for lite0 the FPN's (N,96,16,16)) are read on real
training crops turned at random (the real-crop caches `handtrain detnet` builds; never a
held-back person's), pooled 4x4, and a two-layer head (-> 256 -> 2, ReLU) is fitted on them by
torch; it is written into the file as an AveragePool, a Flatten and two Gemms (float32, the
features' standardisation folded into the first). Every output the file had answers to the bit
as before (checked on crops; nothing is written otherwise).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from handmocap.perception.crops import CROP, angle_apart, hand_angle
from handmocap.perception.detnet_runner import DetNetRunner
from handmocap.perception.hand_finder import to_input_tensor
from handmocap.perception.onnx_models import check_session, file_sha256

OUTPUT = "hand_angle"
POOL = 4                 # the features are averaged over POOL x POOL cells of the grid
HIDDEN = 256


def turned_crops(real, idx, rng, turns=1):
    """Crops (n*turns,128,128,3) uint8 of the real-crop cache rows `idx`, shown as right hands
    at the detector's scale x U(0.9, 1.15), each turned by a random angle and then by 0, 90, ...
    degrees more; and the hand's angle in each, (n,turns) radians (crops.hand_angle)."""
    from handmocap.training import detnet_data, real_data
    side, c = detnet_data.CTX_CROP_SIDE, (detnet_data.CTX - 1) / 2
    images, angles = [], []
    for i in idx:
        a, scale = rng.uniform(-180, 180), rng.uniform(0.9, 1.15)
        for k in range(turns):
            M = real_data.crop_affine(c, c, side * scale, CROP, a + 90 * k, not real["right"][i])
            images.append(real_data.warp(real["image"][i], M))
            angles.append(hand_angle(real_data.apply_affine(M, real["uv"][i])))
    return np.asarray(images), np.asarray(angles).reshape(len(idx), turns)


def feature_tensor(model):
    """Name of the tensor the heatmap head reads beside its coordinate channels: the first input
    of the Concat whose second input is those channels (an Expand) in an exported DetNet."""
    made_by = {out: node for node in model.graph.node for out in node.output}
    for node in model.graph.node:
        if node.op_type == "Concat" and len(node.input) == 2 and \
                getattr(made_by.get(node.input[1]), "op_type", None) == "Expand":
            return node.input[0]
    raise ValueError("no Concat of features and coordinate channels: not an exported DetNet")


def with_feature_output(model, name):
    """A copy of the DetNet ModelProto `model` that also outputs the tensor `name`."""
    import onnx
    copy = onnx.ModelProto()
    copy.CopyFrom(model)
    copy.graph.output.append(onnx.helper.make_empty_tensor_value_info(name))
    return copy


def feature_side(model, name):
    """The grid side of the feature tensor `name` of the DetNet ModelProto `model` (one crop read)."""
    s = model.graph.input[0].type.tensor_type.shape.dim[-1].dim_value
    x = np.zeros((1, 3, s, s), np.float32)
    return check_session(with_feature_output(model, name).SerializeToString()).run([name], {model.graph.input[0].name: x})[0].shape[-1]


def pooled_features(path, images, batch=64):
    """(n, C*POOL*POOL) float32: the DetNet file's feature_tensor on crops images (n,S,S,3) uint8
    RGB, averaged over POOL x POOL cells (as the grafted AveragePool does)."""
    import onnx
    model = onnx.load(str(path))
    name = feature_tensor(model)
    session = check_session(with_feature_output(model, name).SerializeToString())
    out = []
    for k in range(0, len(images), batch):
        f = session.run([name], {model.graph.input[0].name: to_input_tensor(images[k:k + batch])})[0]
        n, c, g, _ = f.shape
        out.append(f.reshape(n, c, POOL, g // POOL, POOL, g // POOL).mean(axis=(3, 5)).reshape(n, -1))
    return np.concatenate(out)


def fit(features, angles, epochs=60, seed=0):
    """The head fitted on features (n,d) -> angles (n,) radians: (W1 (256,d), b1, W2 (2,256), b2)
    float32, with the features' standardisation folded into W1, b1."""
    import torch
    import torch.nn as nn
    import torch.nn.functional as F
    torch.manual_seed(seed)
    mu, sd = features.mean(0), features.std(0) + 1e-6
    X = torch.tensor((features - mu) / sd, dtype=torch.float32)
    Y = torch.tensor(np.stack([np.cos(angles), np.sin(angles)], 1), dtype=torch.float32)
    head = nn.Sequential(nn.Dropout(0.2), nn.Linear(X.shape[1], HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, 2))
    opt = torch.optim.AdamW(head.parameters(), 1e-3, weight_decay=1e-2)
    for _ in range(epochs):
        perm = torch.randperm(len(X))
        for b in range(0, len(X), 256):
            j = perm[b:b + 256]
            loss = F.mse_loss(head(X[j]), Y[j])
            opt.zero_grad()
            loss.backward()
            opt.step()
    W1, b1 = head[1].weight.detach().numpy().astype(np.float64), head[1].bias.detach().numpy().astype(np.float64)
    W1f = W1 / sd                                   # W1 ((x - mu) / sd) + b1 = (W1 / sd) x + (b1 - (W1 / sd) mu)
    return (W1f.astype(np.float32), (b1 - W1f @ mu).astype(np.float32),
            head[3].weight.detach().numpy().astype(np.float32), head[3].bias.detach().numpy().astype(np.float32))


def graft(src, out, weights, check_crops=16):
    """Write the DetNet file `src` with the head `weights` (fit's) as output OUTPUT to `out`;
    checks on `check_crops` random crops that every output `src` had answers to the bit as
    before (nothing written otherwise). Returns out."""
    import onnx
    from onnx import helper, numpy_helper
    src, out = Path(src), Path(out)
    model = onnx.load(str(src))
    feat = feature_tensor(model)
    names = [o.name for o in model.graph.output]     # the outputs src had, checked below
    W1, b1, W2, b2 = weights
    g = model.graph
    g.initializer.extend([numpy_helper.from_array(a, f"{OUTPUT}/{n}") for a, n in
                          ((W1, "W1"), (b1, "b1"), (W2, "W2"), (b2, "b2"))])
    cells = feature_side(model, feat) // POOL
    g.node.extend([
        helper.make_node("AveragePool", [feat], [f"{OUTPUT}/pooled"], kernel_shape=[cells, cells], strides=[cells, cells],
                         name=f"{OUTPUT}/pool"),
        helper.make_node("Flatten", [f"{OUTPUT}/pooled"], [f"{OUTPUT}/flat"], axis=1, name=f"{OUTPUT}/flatten"),
        helper.make_node("Gemm", [f"{OUTPUT}/flat", f"{OUTPUT}/W1", f"{OUTPUT}/b1"], [f"{OUTPUT}/hidden"], transB=1,
                         name=f"{OUTPUT}/fc1"),
        helper.make_node("Relu", [f"{OUTPUT}/hidden"], [f"{OUTPUT}/relu"], name=f"{OUTPUT}/relu"),
        helper.make_node("Gemm", [f"{OUTPUT}/relu", f"{OUTPUT}/W2", f"{OUTPUT}/b2"], [OUTPUT], transB=1,
                         name=f"{OUTPUT}/fc2")])
    g.output.append(helper.make_tensor_value_info(OUTPUT, onnx.TensorProto.FLOAT, ["N", 2]))
    model.doc_string = f"{model.doc_string} + {OUTPUT} head (handmocap.training.angle_head)".strip()
    onnx.helper.set_model_props(model, {**{p.key: p.value for p in model.metadata_props},
                                        "angle_head_source": src.name, "angle_head_source_sha256": file_sha256(src)})
    onnx.checker.check_model(model)
    s = g.input[0].type.tensor_type.shape.dim[-1].dim_value
    x = np.random.default_rng(0).random((check_crops, 3, s, s), dtype=np.float32)
    before = check_session(src).run(names, {g.input[0].name: x})
    after = check_session(model.SerializeToString()).run(names + [OUTPUT], {g.input[0].name: x})
    for name, a, b in zip(names, before, after):
        if not np.array_equal(a, b, equal_nan=True):
            raise RuntimeError(f"{name} of {src} changed with the head grafted on (largest gap "
                               f"{np.nanmax(np.abs(a - b)):.3g}); nothing written")
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(out))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src", type=Path, help="an exported DetNet file (e.g. models/detnet_lite0_int8.onnx)")
    p.add_argument("--out", type=Path, required=True, help="where the file with the head goes")
    p.add_argument("--crops", type=int, default=12000, help="training crops the head is fitted on (at most)")
    args = p.parse_args(argv)
    from handmocap.training import detnet_data, real_data
    real = detnet_data.load_real(real_data.SHARED_DATA)
    if real is None:
        raise SystemExit(f"no data pack at {real_data.SHARED_DATA}: the head is fitted on its real crops")
    source = real["source"].astype(str)
    people = np.char.startswith(source, detnet_data.HELD_BACK_SOURCE)
    train = np.random.default_rng(0).permutation(np.flatnonzero(~real["held"] & ~people))[:args.crops]
    test = np.flatnonzero(people & ~np.char.startswith(source, detnet_data.HELD_BACK_SOURCE + "11k/"))
    images, angles = turned_crops(real, train, np.random.default_rng(1))
    print(f"reading {len(train)} training crops' features", flush=True)
    weights = fit(pooled_features(args.src, images), angles[:, 0])
    graft(args.src, args.out, weights)
    images, angles = turned_crops(real, test, np.random.default_rng(2))
    runner = DetNetRunner.load(args.out)
    cs = np.concatenate([runner(images[k:k + 64])[OUTPUT] for k in range(0, len(images), 64)])
    err = angle_apart(np.arctan2(cs[:, 1], cs[:, 0]), angles[:, 0])
    sure = np.linalg.norm(cs, axis=1) >= 0.5
    print(f"wrote {args.out}: on {len(test)} held-back crops turned at random, the angle is more than 45 degrees "
          f"off on {np.mean(err > np.pi / 4):.1%} ({np.mean(err[sure] > np.pi / 4):.1%} of the {sure.mean():.0%} "
          f"where |{OUTPUT}| >= 0.5), median {np.degrees(np.median(err)):.1f} deg")


if __name__ == "__main__":
    main()
