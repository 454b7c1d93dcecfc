"""Pieces every training script shares (torch-free)."""
import math


def warmup_cosine_lr(it: int, base_lr: float, total: int, warmup: int = 0, floor: float = 0.01) -> float:
    """Learning rate at iteration `it`: linear warm-up over `warmup` iterations, then a cosine
    from base_lr down to floor * base_lr at iteration `total` (and flat after it)."""
    if it < warmup:
        return base_lr * (it + 1) / warmup
    t = min((it - warmup) / max(1, total - warmup), 1.0)
    return base_lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t)))


def add_pretrained_arguments(p):
    """The fine-tuning arguments of a network whose backbone starts from ImageNet weights
    (efficientnet_lite.LiteTrunk): --freeze-blocks and --backbone-lr, for DetNet's and the
    finder's trainers alike."""
    p.add_argument("--freeze-blocks", type=int, default=None, metavar="K",
                   help="lite0, lite2: the stem and the first K blocks keep their ImageNet weights and BatchNorm statistics "
                        "(default: the blocks up to stride 4, edges and colours: lite0's 3, lite2's 4); also saves "
                        "their backward pass")
    p.add_argument("--backbone-lr", type=float, default=0.3, metavar="S",
                   help="lite0, lite2: the pretrained blocks learn at S x --lr, the new layers at --lr (default %(default)s)")
