"""Pieces every training script shares (torch-free)."""
import math


def warmup_cosine_lr(it: int, base_lr: float, total: int, warmup: int = 0, floor: float = 0.01) -> float:
    """Learning rate at iteration `it`: linear warm-up over `warmup` iterations, then a cosine
    from base_lr down to floor * base_lr at iteration `total` (and flat after it)."""
    if it < warmup:
        return base_lr * (it + 1) / warmup
    t = min((it - warmup) / max(1, total - warmup), 1.0)
    return base_lr * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t)))
