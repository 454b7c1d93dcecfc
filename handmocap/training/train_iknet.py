"""Train IKNet on CPU and export it (`handtrain iknet`; to RUN_DIR/iknet.onnx unless --export says where).

    handtrain iknet                      # from scratch (runs/iknet/ is replaced)
    handtrain iknet --resume             # continue runs/iknet/last.pt to --iters
    handtrain iknet --export-only        # write the ONNX file from runs/iknet/last.pt

A float32 export is followed by its static int8 copy beside it (NAME_int8.onnx, by
handmocap.training.quantize_iknet): models/iknet_int8.onnx, the file IKSolver.load opens by default,
always comes from the models/iknet.onnx next to it.

Each batch mixes (paper Sec. 3.3):
* pose samples (pose_data.PoseSampler): clean joints with rotation targets, all four losses;
* noisy samples ("3DPosData"): the same kind of poses with emulated detector errors
  (pose_data.corrupt_joints) as input, supervised by the clean joints through FK (L_xyz);
  --noisy-source FILE.npz uses a detector's predictions on rendered images of known poses
  instead (pose_data.PositionPairs.from_npz), once a trained detector exists;
* real joint sequences (pose_data.REAL_TRAIN, MediaPipe world landmarks) as positional
  supervision, L_xyz with the rest pose fitted to each frame's bone ratios; skipped with a
  note when the shared data pack (../shared/data) is absent.
Every batch is made from numpy generator [seed, iteration], so a resumed run sees exactly
the batches the uninterrupted run would have. Validation uses its own seed, never a
training batch.
"""
import os
import time
from pathlib import Path

import numpy as np

from handmocap.perception.ik_solver import FLOAT32_MODEL, iknet_inputs
from handmocap.training.pose_data import (REAL_TRAIN, SHARED_DATA, BatchMaker, PoseSampler, PositionPairs, corrupt_joints,
                                         load_real_sequences)
from handmocap.perception.rotations import quat_angle_between
from handmocap.training.training import warmup_cosine_lr

RUN_DIR = Path("runs/iknet")
VAL_SEED = 987_654_321


def add_arguments(p):
    p.add_argument("--iters", type=int, default=20000, help="total iterations (a resumed run continues to this)")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--lr", type=float, default=1e-3, help="Adam, cosine decay to lr/100 after 200 warm-up iterations")
    p.add_argument("--share-noisy", type=float, default=0.35, help="share of each batch with noisy input")
    p.add_argument("--share-real", type=float, default=0.15, help="share of each batch from real sequences")
    p.add_argument("--noisy-source", default="emulated",
                   help="'emulated' (corrupt_joints) or an .npz of detector predictions (pred, target[, rest])")
    p.add_argument("--share-detector", type=float, default=1.0,
                   help="with a --noisy-source file: the share of the noisy samples taken from it (the rest emulated)")
    p.add_argument("--no-real", action="store_true", help="do not use the real joint sequences")
    p.add_argument("--data", type=Path, default=SHARED_DATA, help="real data pack (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--val-every", type=int, default=1000)
    p.add_argument("--ckpt-every", type=int, default=250)
    p.add_argument("--run-dir", type=Path, default=RUN_DIR)
    p.add_argument("--export", type=Path, default=None,
                   help=f"ONNX output (default RUN_DIR/iknet.onnx: the shipped {FLOAT32_MODEL.name} is replaced only "
                        f"when you name it, --export models/iknet.onnx); its static int8 copy NAME_int8.onnx "
                        f"is written beside it")
    p.add_argument("--float16", action="store_true", help="store the ONNX weights in float16")
    p.add_argument("--int8", action="store_true",
                   help="export with int8 dynamic quantization (activation ranges per batch: a hand's output "
                        "depends on the other hands in the batch; the default int8 file is static, see quantize_iknet)")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR/last.pt")
    p.add_argument("--export-only", action="store_true", help="export RUN_DIR/last.pt and stop")


def to_torch(batch):
    import torch
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in batch.items() if k != "frame"}


def validation_set(model, n=2000):
    """Fixed held-out synthetic poses (seed VAL_SEED): clean and with emulated noise."""
    rng = np.random.default_rng(VAL_SEED)
    poses = PoseSampler(model).sample(n, rng)
    return poses, corrupt_joints(poses["xyz"], rng)


def predict(net, xyz, rest, batch=1000):
    """Torch IKNet (eval mode) on normalized joints -> (N,21,4) camera-axes quaternions."""
    import torch
    from handmocap.perception.ik_solver import iknet_outputs
    out = []
    with torch.no_grad():
        for i in range(0, len(xyz), batch):
            features, frame = iknet_inputs(xyz[i:i + batch], rest[i:i + batch])
            out.append(iknet_outputs(net(torch.from_numpy(features)).numpy(), frame))
    return np.concatenate(out)


def validate(net, model, val):
    from handmocap.perception.ik_solver import normalize_joints
    from handmocap.perception.kinematics import forward_kinematics
    poses, noisy = val
    was_training = net.training
    net.eval()
    q_clean, q_noisy = predict(net, poses["xyz"], poses["rest"]), predict(net, noisy, poses["rest"])
    net.train(was_training)
    mm = 95.0
    fk = lambda q: normalize_joints(forward_kinematics(q, poses["rest"]))  # noqa: E731
    return {"rot_deg": float(np.degrees(quat_angle_between(q_clean, poses["quats"]))[:, 1:].mean()),
            "fk_mm": float(np.linalg.norm(fk(q_clean) - poses["xyz"], axis=-1).mean() * mm),
            "noisy_fk_mm": float(np.linalg.norm(fk(q_noisy) - poses["xyz"], axis=-1).mean() * mm),
            "noise_mm": float(np.linalg.norm(noisy - poses["xyz"], axis=-1).mean() * mm)}


def main(args):
    if args.export is None:   # never the shipped model by default: a trial run must not replace it
        args.export = args.run_dir / "iknet.onnx"
    import torch
    from tqdm import tqdm

    from handmocap.perception.hand_model import HandModel
    from handmocap.training.iknet import IKNet, iknet_losses
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    model = HandModel.load()
    net = IKNet()
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    ckpt_path = args.run_dir / "last.pt"
    start, history = 0, []
    if args.resume or args.export_only:
        if not ckpt_path.exists():
            raise SystemExit(f"no checkpoint at {ckpt_path}: train from scratch with `handtrain iknet`")
        ckpt = torch.load(ckpt_path, weights_only=False)
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        start, history = ckpt["iteration"], ckpt["history"]
        print(f"resumed {ckpt_path} at iteration {start}")
    if args.export_only:
        net.eval()
        export(net, args)
        return

    noisy_pairs = None if args.noisy_source == "emulated" else PositionPairs.from_npz(args.noisy_source, model)
    real_pairs = None
    if not args.no_real:
        sequences = load_real_sequences(REAL_TRAIN, args.data)
        if sequences:
            real_pairs = PositionPairs.from_sequences(sequences, model)
            print(f"real joint sequences: {len(sequences)} clips, {len(real_pairs)} frames from {args.data}")
        else:
            print(f"note: no real joint sequences under {args.data}; training on synthetic data only")
    maker = BatchMaker(model, noisy_pairs, real_pairs, args.share_noisy, args.share_real, args.share_detector)
    val = validation_set(model)
    args.run_dir.mkdir(parents=True, exist_ok=True)

    def save(it):
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save({"model": net.state_dict(), "optimizer": opt.state_dict(), "iteration": it,
                    "history": history, "args": {k: str(v) for k, v in vars(args).items()}}, tmp)
        os.replace(tmp, ckpt_path)

    net.train()
    bar = tqdm(range(start, args.iters), initial=start, total=args.iters, desc="iknet", dynamic_ncols=True)
    t0 = time.monotonic()
    for it in bar:
        for group in opt.param_groups:
            group["lr"] = warmup_cosine_lr(it, args.lr, args.iters, warmup=200, floor=0.01)
        b = to_torch(maker.make(args.batch, np.random.default_rng([args.seed, it])))
        raw = net(b["features"])
        losses = iknet_losses(raw, b["xyz"], b["rest"], b["quat"], b["has_quat"])
        loss = losses["cos"] + losses["l2"] + losses["xyz"] + losses["norm"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if it % 20 == 0:
            bar.set_postfix({k: f"{v.item():.4f}" for k, v in losses.items()})
        done = it + 1
        if done % args.val_every == 0 or done == args.iters:
            metrics = validate(net, model, val)
            history.append({"iteration": done, "seconds": time.monotonic() - t0, **metrics})
            bar.write(f"iter {done}: val rot {metrics['rot_deg']:.2f} deg, FK {metrics['fk_mm']:.2f} mm; "
                      f"noisy FK {metrics['noisy_fk_mm']:.2f} mm (noise {metrics['noise_mm']:.2f} mm)")
        if done % args.ckpt_every == 0 or done == args.iters:
            save(done)
    net.eval()
    export(net, args)
    print(f"after {args.iters} iterations")


def export(net, args):
    """ONNX file(s) of the trained network: args.export, and for a float32 export its static
    int8 copy beside it (so the int8 default never lags the float32 network)."""
    from handmocap.training.iknet import export_onnx
    args.export.parent.mkdir(parents=True, exist_ok=True)
    export_onnx(net, args.export, float16=args.float16, int8=args.int8)
    print(f"exported {args.export} ({args.export.stat().st_size / 1e6:.1f} MB)")
    if not (args.float16 or args.int8):
        from handmocap.training.quantize_iknet import quantize
        int8 = args.export.with_name(args.export.stem + "_int8.onnx")
        quantize(args.export, int8, data_root=args.data)
        print(f"exported {int8} ({int8.stat().st_size / 1e6:.1f} MB, static int8: python -m handmocap.training.quantize_iknet)")
