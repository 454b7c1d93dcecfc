"""One DetNet from the mean of the weights of several fine-tunes of the same network.

    python -m handmocap.training.average_detnet --out runs/detnet/avg/final.onnx [--weights-out W.pt] \\
        runs/detnet/a/last.pt runs/detnet/b/last.pt runs/detnet/c/last.pt

Checkpoints are a run's last.pt or the float16 weights files `--weights-out` writes
(models/detnet_lite0.pt, models/candidates/*.pt); `--weights-out` writes the mean's, which
`handtrain detnet --init-from` trains on from.

Why: fine-tunes that start from one network (`handtrain detnet --init-from`) with other
seeds or loss settings stay in one basin of the loss, and the mean of their weights (a
"model soup", Wortsman et al., ICML 2022) is usually at least as good as the best of them
on data none of them saw, at no extra training. Each 4,000-iteration CPU run moves the
held-back figures by about their noise; the mean of several cancels part of it
(docs/experiment_log.md, "Session 27").

Every floating-point tensor of the state dict is averaged, BatchNorm running statistics
included (the fine-tunes' statistics differ little; averaged, they match the averaged
weights well enough that the held-out metrics come out as good, see the log). Integer
tensors (BatchNorm's batch counters) are the first checkpoint's. The read-out (`refine`)
is the first checkpoint's. Checkpoints of other backbones, or with and without an optional
part (fine heatmaps, presence map or branch: detnet.ARCH), are refused: their weights do not correspond.
"""
import argparse
from pathlib import Path


def average_states(states):
    """The mean of state dicts [{name: tensor}] of one architecture (floating tensors; the
    others are the first's). A ValueError naming the first key or shape that differs."""
    first = states[0]
    for i, s in enumerate(states[1:], 1):
        if s.keys() != first.keys():
            diff = sorted(set(s) ^ set(first))
            raise ValueError(f"checkpoint {i} has other tensors than checkpoint 0 (e.g. {diff[0]})")
        for k, v in s.items():
            if v.shape != first[k].shape:
                raise ValueError(f"checkpoint {i}: {k} is {tuple(v.shape)}, checkpoint 0's {tuple(first[k].shape)}")
    return {k: (sum(s[k].double() for s in states) / len(states)).to(v.dtype) if v.is_floating_point() else v
            for k, v in first.items()}


def average_checkpoints(paths):
    """(DetNet with the mean weights, refine, backbone) of `handtrain detnet` checkpoints
    (last.pt, or float16 weights files)."""
    import torch

    from handmocap.training.detnet import ARCH, DetNet       # ARCH: what a checkpoint records; absent: False
    from handmocap.training.detnet_init import recorded_parts
    if len(paths) < 2:
        raise ValueError(f"averaging needs at least two checkpoints, got {len(paths)}")
    ckpts = []
    for p in paths:
        if not Path(p).is_file():
            raise FileNotFoundError(f"{p}: no such checkpoint (a `handtrain detnet` run's last.pt)")
        ckpts.append(torch.load(p, weights_only=False, map_location="cpu"))
    shapes = {(c.get("backbone"), c.get("fine") or False, *recorded_parts(c).values()) for c in ckpts}
    if len(shapes) > 1:
        raise ValueError(f"the checkpoints are of different networks ((backbone, {', '.join(ARCH)})): "
                         f"{sorted(shapes)}")
    backbone, *options = shapes.pop()
    net = DetNet(backbone, **dict(zip(ARCH, options)))
    net.load_state_dict(average_states([c["model"] for c in ckpts]))
    return net.eval(), ckpts[0].get("refine", "softmax"), backbone


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+", type=Path, help="`handtrain detnet` checkpoints (RUN_DIR/last.pt)")
    p.add_argument("--out", type=Path, required=True, help="the averaged network's ONNX file")
    p.add_argument("--weights-out", type=Path, help="also its float16 weights (what --init-from trains on from)")
    args = p.parse_args(argv)
    from handmocap.training.detnet import export_onnx
    from handmocap.training.detnet_init import write_weights
    try:
        net, refine, backbone = average_checkpoints(args.checkpoints)
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"average_detnet: {e}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    export_onnx(net, args.out, refine)
    print(f"wrote {args.out}: the mean of {len(args.checkpoints)} checkpoints (refine {refine})")
    if args.weights_out:
        args.weights_out.parent.mkdir(parents=True, exist_ok=True)
        write_weights(args.weights_out, net, refine, backbone, iteration=0,
                      mean_of=[str(c) for c in args.checkpoints])


if __name__ == "__main__":
    main()
