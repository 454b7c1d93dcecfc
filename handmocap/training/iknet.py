"""IKNet in PyTorch (paper Sec. 3.3), for training and export only; inference is
handmocap.perception.ik_solver (onnxruntime, no torch).

    features (N, 252) = [X, D, X_ref, D_ref]  (see ik_solver.iknet_inputs)
    6 x [Linear 1024 -> BatchNorm -> sigmoid] -> Linear 84 -> raw quaternions (N, 21, 4)

Losses (Eq. 9-13), each summed over joints and averaged over the samples it applies to;
q = raw / |raw|, q_gt the target, x_gt target joints:
    L_cos  = 1 - |<q_gt, q>|            (= 1 - real(q_gt * q^-1), sign-free: q ~ -q)
    L_l2   = min |q_gt -+ q|^2
    L_xyz  = |x_gt - FK(q)|^2           (joints re-centred on joint 9; normalized units)
    L_norm = |1 - |raw|^2|
L_cos and L_l2 need rotation targets (pose samples); L_xyz applies to every sample, so it
is all that noisy inputs and real joint sequences are supervised by.

forward_kinematics is handmocap.perception.kinematics.forward_kinematics written in torch, with the
hand model's rigid palm: the bones 0 -> 1, 5, 9, 13, 17 turn with the wrist (q_0), as in
HandModel.forward, whatever the network says for q_1, q_5, q_9, q_13, q_17.
"""
import numpy as np
import torch
from torch import nn

from handmocap.perception.skeleton import NUM_JOINTS, PARENTS

PALM_BONES = (1, 5, 9, 13, 17)
# bone rotation each joint is placed with: q_j, except the palm bones which use q_0
EFFECTIVE_BONE = np.array([0 if j in PALM_BONES else j for j in range(NUM_JOINTS)])
NUM_INPUTS = 4 * NUM_JOINTS * 3


class IKNet(nn.Module):
    def __init__(self, width=1024, depth=6):
        super().__init__()
        layers, size = [], NUM_INPUTS
        for _ in range(depth):
            layers += [nn.Linear(size, width), nn.BatchNorm1d(width), nn.Sigmoid()]
            size = width
        self.body = nn.Sequential(*layers)
        self.head = nn.Linear(size, NUM_JOINTS * 4)

    def forward(self, features):
        """(N, 252) -> raw (unnormalized) quaternions (N, 21, 4)."""
        return self.head(self.body(features)).view(-1, NUM_JOINTS, 4)


def quat_to_matrix(q):
    """(..., 4) quaternions (w, x, y, z), normalized here -> (..., 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).view(q.shape[:-1] + (3, 3))


def forward_kinematics(quats, rest, rigid_palm=True):
    """Joints (N, 21, 3) from bone quaternions (N, 21, 4) and rest joints (N, 21, 3):
    x_0 = rest_0, x_j = x_parent(j) + R(q_j) (rest_j - rest_parent(j))."""
    R = quat_to_matrix(quats)
    if rigid_palm:
        R = R[:, EFFECTIVE_BONE]
    offsets = rest - rest[:, np.maximum(PARENTS, 0)]
    bone_vecs = (R @ offsets.unsqueeze(-1)).squeeze(-1)                    # (N,21,3)
    joints = [rest[:, 0]]
    for j in range(1, NUM_JOINTS):
        joints.append(joints[PARENTS[j]] + bone_vecs[:, j])
    return torch.stack(joints, dim=1)


def iknet_losses(raw, xyz_target, rest, quat_target=None, has_quat=None):
    """Dict of the four loss terms (scalars).

    raw (N,21,4) network output; xyz_target (N,21,3) normalized joints (joint 9 at 0);
    rest (N,21,3) normalized rest joints; quat_target (N,21,4) and has_quat (N,) bool mark
    the samples with rotation targets.
    """
    norm2 = (raw * raw).sum(-1)
    q = raw / norm2.clamp_min(1e-12).sqrt().unsqueeze(-1)
    joints = forward_kinematics(q, rest)
    joints = joints - joints[:, 9:10]
    out = {"norm": (1 - norm2).abs().sum(-1).mean(),
           "xyz": ((joints - xyz_target) ** 2).sum((-1, -2)).mean()}
    if quat_target is not None and bool(has_quat.any()):
        q, g = q[has_quat], quat_target[has_quat]
        dot = (q * g).sum(-1)
        out["cos"] = (1 - dot.abs()).sum(-1).mean()
        out["l2"] = (2 - 2 * dot.abs()).sum(-1).mean()      # min |g -+ q|^2 for unit q
    else:
        out["cos"] = out["l2"] = raw.new_zeros(())
    return out


# -------------------------------------------------------------------- export
def folded_layers(model):
    """[(W (out,in), b (out,)) float32 numpy] per Linear, eval-mode BatchNorm folded in."""
    out, mods = [], list(model.body) + [model.head]
    for i, m in enumerate(mods):
        if not isinstance(m, nn.Linear):
            continue
        W, b = m.weight.detach().double().numpy(), m.bias.detach().double().numpy()
        bn = mods[i + 1] if i + 1 < len(mods) and isinstance(mods[i + 1], nn.BatchNorm1d) else None
        if bn is not None:
            scale = bn.weight.detach().double().numpy() / np.sqrt(bn.running_var.double().numpy() + bn.eps)
            W, b = W * scale[:, None], (b - bn.running_mean.double().numpy()) * scale + bn.bias.detach().double().numpy()
        out.append((W.astype(np.float32), b.astype(np.float32)))
    return out


def export_onnx(model, path, float16=False, int8=False, opset=17):
    """Write the network as ONNX: input `features` (N,252) float32, output `quat_raw` (N,84)
    float32 (un-normalized; ik_solver normalizes). Gemm + Sigmoid, BatchNorm folded.
    float16: store the weights in half precision (Cast to float32 at load, computed in float32).
    int8: onnxruntime dynamic quantization (int8 weights per output channel, activations
    quantized on the fly): a quarter of the bytes to stream per hand."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    layers = folded_layers(model)
    nodes, inits, x = [], [], "features"
    for i, (W, b) in enumerate(layers):
        names = [f"W{i}", f"b{i}"]
        for name, arr in zip(names, (W, b)):
            if float16:
                inits.append(numpy_helper.from_array(arr.astype(np.float16), name + "_f16"))
                nodes.append(helper.make_node("Cast", [name + "_f16"], [name], to=TensorProto.FLOAT))
            else:
                inits.append(numpy_helper.from_array(arr, name))
        last = i == len(layers) - 1
        y = "quat_raw" if last else f"h{i}"
        nodes.append(helper.make_node("Gemm", [x, *names], [y if last else y + "_lin"], transB=1))
        if not last:
            nodes.append(helper.make_node("Sigmoid", [y + "_lin"], [y]))
        x = y
    graph = helper.make_graph(
        nodes, "iknet",
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, ["N", NUM_INPUTS])],
        [helper.make_tensor_value_info("quat_raw", TensorProto.FLOAT, ["N", NUM_JOINTS * 4])], inits)
    onnx_model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)],
                                   producer_name="handmocap.training.train_iknet")
    onnx_model.ir_version = 8
    onnx.checker.check_model(onnx_model)
    if not int8:
        onnx.save(onnx_model, str(path))
        return
    import tempfile
    from pathlib import Path

    from onnxruntime.quantization import QuantType, quantize_dynamic
    with tempfile.TemporaryDirectory() as tmp:
        plain = Path(tmp) / "iknet_f32.onnx"
        onnx.save(onnx_model, str(plain))
        quantize_dynamic(str(plain), str(path), weight_type=QuantType.QInt8, per_channel=True)
