"""Export a DetNet file again with this code's read-out (`detnet.read_out`, `export_onnx`):
the network recovered from the file (`detnet_init.state_from_onnx`), so its maps stay as
they were and only the read-out inside the graph changes.

    python scripts/reexport_detnet.py models/detnet.onnx [--out models/detnet.onnx] [--refine softmax]
    python -m handmocap.training.quantize_detnet          # then the int8 copy, from the new float file

Prints the largest output differences against the file as it was, on 64 crops.
"""
import argparse
import tempfile
from pathlib import Path

import numpy as np

from handmocap.perception.detnet_runner import DetNetRunner
from handmocap.training.detnet import REFINE, DetNet, export_onnx
from handmocap.training.detnet_init import state_from_onnx


def crops(n=64, seed=0):
    """(n,128,128,3) uint8: smooth random images (the BatchNorm refit needs varied inputs,
    not hands; the refit is exact in eval mode whatever they are)."""
    import cv2
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (n, 16, 16, 3), dtype=np.uint8)
    return np.stack([cv2.resize(s, (128, 128), interpolation=cv2.INTER_CUBIC) for s in small])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src", type=Path)
    p.add_argument("--out", type=Path, help="default: src, replaced")
    p.add_argument("--refine", default="softmax", choices=REFINE)
    args = p.parse_args()
    out = args.out or args.src
    images = crops()
    state, backbone = state_from_onnx(args.src, images)
    net = DetNet(backbone, fine=any(k.startswith("fine.") for k in state))
    net.load_state_dict(state)
    with tempfile.TemporaryDirectory() as tmp:
        new = Path(tmp) / "detnet.onnx"
        export_onnx(net, new, args.refine)
        before, after = DetNetRunner.load(args.src)(images), DetNetRunner.load(new)(images)
        out.write_bytes(new.read_bytes())
    print(f"wrote {out} ({args.refine} read-out, {backbone}); largest change on {len(images)} crops: " +
          ", ".join(f"{k} {np.abs(before[k] - after[k]).max():.3g}" for k in before))


if __name__ == "__main__":
    main()
