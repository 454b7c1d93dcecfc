"""A network of its own for the hand's side: does a side classifier that shares nothing with
the keypoint heads say the side of strangers' hands better than DetNet's handedness head?

    python research/side_net.py --iters 5000 [--run-dir runs/side_net] [--resume] [--threads 2]
    python research/side_net.py --init-detnet models/detnet.onnx --lr 3e-4 --run-dir runs/side_net_ft

Session 13 guessed that keypoint heads serving both sides take chirality out of the shared
features the handedness head reads, and that "a handedness head of its own on the crop"
might do better. This trains one: the `fast` backbone (0.16 M parameters, no weights shared
with DetNet; or, with --init-detnet, a copy of DetNet's backbone and head that from then on
learns the side alone) and a head that reads a coarse 4x4 map (chirality is layout: DetNet's own head
notes a global mean stays at chance), on the crops DetNet trains on, half shown as left
hands (detnet_batches.BatchMaker: rendered crops and every training person's real crops,
turned upright +-60 degrees, colour jitter, motion blur and degradation), binary
cross-entropy on the shown side.

It is scored as research/side_cues.py scores DetNet's head: on the held-out real crops
(detnet_eval.real_val_set, upright), each read as it is (a right hand) and flipped (a
left one); the vote says right when the net's logit on the crop exceeds its logit on the
flip. Printed per group beside DetNet's head, every --val-every iterations.
"""
import argparse
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from handmocap.perception.tracks import logit
from handmocap.training.detnet import BACKBONES, conv_bn
from handmocap.training.pose_data import SHARED_DATA
from handmocap.training.detnet_batches import BatchMaker, degrade, motion_blur, to_torch
from handmocap.training.detnet_data import load_real, load_synth, synth_dirs
from handmocap.training.detnet_eval import heldout_groups
from handmocap.training.detnet_init import load_matching, state_from_onnx

ROOT = Path(__file__).resolve().parents[1]


class SideNet(nn.Module):
    """(N,3,128,128) RGB in [0,1] -> (N,) logit that the hand shown is a right hand. Its
    modules carry DetNet's names (backbone, chirality, handedness_head), so with
    backbone="fast-deep" and layout=8 a DetNet's weights load into it."""

    def __init__(self, backbone="fast", layout=16):
        super().__init__()
        self.backbone, c, _ = BACKBONES[backbone]()
        self.chirality = conv_bn(c, layout, 1)
        self.handedness_head = nn.Sequential(nn.Linear(layout * 16, 64), nn.ReLU(inplace=True), nn.Linear(64, 1))

    def forward(self, image):
        feat = self.chirality(self.backbone(image * 2.0 - 1.0))
        return self.handedness_head(F.adaptive_avg_pool2d(feat, 4).flatten(1))[:, 0]


@torch.no_grad()
def side_logits(net, images, batch=256):
    """(N,) logits of net on uint8 crops (N,128,128,3)."""
    net.eval()
    out = [net((torch.from_numpy(np.ascontiguousarray(images[i:i + batch])).permute(0, 3, 1, 2).float() / 255.0)
               .contiguous(memory_format=torch.channels_last)) for i in range(0, len(images), batch)]
    net.train()
    return torch.cat(out).numpy()


def detnet_votes(images, flipped, detnet_path):
    """(N,) DetNet's mirror vote (head logit on the crops `images` (N,128,128,3) minus on
    them `flipped`) on the held-out crops."""
    from handmocap.training.quantize_detnet import OnnxNet
    net = OnnxNet(str(detnet_path))
    return logit(net.predict(images)[2]) - logit(net.predict(flipped)[2])


def report(it, votes, detnet_vote, groups):
    cells = [f"{np.mean(votes[m] > 0):.1%} (head {np.mean(detnet_vote[m] > 0):.1%}, n={m.sum()})"
             for m in groups.values()]
    print(f"it {it}: " + "; ".join(f"{g} {c}" for g, c in zip(groups, cells)), flush=True)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--iters", type=int, default=5000)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--data", nargs="+", default=[str(ROOT / "runs/detnet_data/synth_train_*")])
    p.add_argument("--max-synth", type=int, default=16384)
    p.add_argument("--share-real", type=float, default=0.6)
    p.add_argument("--val-every", type=int, default=1000)
    p.add_argument("--run-dir", type=Path, default=ROOT / "runs/side_net")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--detnet", type=Path, default=ROOT / "models/detnet_int8.onnx", help="whose head to compare with")
    p.add_argument("--seed", type=int, default=33)
    p.add_argument("--init-detnet", type=Path, default=None, metavar="ONNX",
                   help="start from this exported DetNet's backbone and handedness head (fast-deep, layout 8) "
                        "instead of from scratch (fast, layout 16)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    from handmocap.training.quantize_detnet import heldout_sets
    synth = load_synth(synth_dirs(args.data), args.max_synth)
    if synth is None:
        raise SystemExit(f"no synthetic shards match {args.data}: `handsynth generate -n 8192 -o "
                         f"runs/detnet_data/synth_train_s33_0 --seed 3300`")
    real = load_real(SHARED_DATA)
    if real is None:
        raise SystemExit(f"this study needs the data pack at {SHARED_DATA}")
    maker = BatchMaker(synth, real, share_real=args.share_real, share_neg=0.0, share_left=0.5, upright=60)
    _, crops = heldout_sets(upright=True)
    groups = heldout_groups(crops["source"])
    flipped = np.ascontiguousarray(crops["image"][:, :, ::-1])
    head_vote = detnet_votes(crops["image"], flipped, args.detnet)

    if args.init_detnet:
        state, backbone = state_from_onnx(args.init_detnet, maker.make(512, np.random.default_rng([args.seed, 2**31]))["image"])
        net = SideNet(backbone, layout=8)
        fresh = load_matching(net, state)
        print(f"started from {args.init_detnet}'s {backbone} backbone and handedness head; fresh: {sorted(fresh) or 'none'}")
    else:
        net = SideNet()
    net = net.to(memory_format=torch.channels_last)      # channels_last: 20-30% faster on the CPU
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda i: min(1.0, (i + 1) / 300) * (0.02 + 0.98 * 0.5 * (1 + np.cos(np.pi * min(i / args.iters, 1.0)))))
    args.run_dir.mkdir(parents=True, exist_ok=True)
    ckpt, start = args.run_dir / "last.pt", 0
    if args.resume and ckpt.exists():
        state = torch.load(ckpt, weights_only=False)
        net.load_state_dict(state["net"]), opt.load_state_dict(state["opt"]), sched.load_state_dict(state["sched"])
        start = state["it"]
        print(f"resumed at iteration {start}")
    print(f"SideNet: {sum(p.numel() for p in net.parameters()) / 1e6:.2f} M parameters; "
          f"{len(synth['image'])} rendered crops, {int((~real['held']).sum())} real training crops")
    t0, losses = time.time(), []
    for it in range(start, args.iters):
        rng = np.random.default_rng([args.seed, it])
        b = maker.make(args.batch, rng)
        hand = b["presence"] > 0
        motion_blur(b["image"], hand, 0.2, rng)
        degrade(b["image"], hand, 0.2, rng)
        t = to_torch(b, rng)
        out = net(t["image"].contiguous(memory_format=torch.channels_last))
        w = t["w_hand"]
        loss = (F.binary_cross_entropy_with_logits(out, t["right"], reduction="none") * w).sum() / w.sum().clamp_min(1e-6)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
        if (it + 1) % 100 == 0:
            print(f"it {it + 1}: loss {np.mean(losses[-100:]):.3f}, {(time.time() - t0) / (it + 1 - start):.2f} s/it",
                  flush=True)
            torch.save({"net": net.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(), "it": it + 1}, ckpt)
        if (it + 1) % args.val_every == 0 or it + 1 == args.iters:
            report(it + 1, side_logits(net, crops["image"]) - side_logits(net, flipped), head_vote, groups)


if __name__ == "__main__":
    main()
