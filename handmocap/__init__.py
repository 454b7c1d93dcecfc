"""handmocap: real-time monocular RGB hand shape and motion capture.

Public entry points (docs/reference.md "In-process, without a graph"), imported on first use so that `import handmocap` stays cheap
for node processes:
    handmocap.HandModel     the bundled open hand model, or a user's MANO file
    handmocap.IKSolver      IKNet (onnxruntime): 3D joints -> global joint rotations
    handmocap.HandTracker   the in-process image -> hand pose pipeline
"""
import importlib

_ENTRY_POINTS = {
    "HandModel": "handmocap.perception.hand_model",
    "IKSolver": "handmocap.perception.ik_solver",
    "HandTracker": "handmocap.perception.tracker",
}

__all__ = list(_ENTRY_POINTS)


def __getattr__(name):
    if name in _ENTRY_POINTS:
        return getattr(importlib.import_module(_ENTRY_POINTS[name]), name)
    raise AttributeError(f"module 'handmocap' has no attribute {name!r}")
