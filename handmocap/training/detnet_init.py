"""Where a DetNet's weights start: a checkpoint of another network (`load_matching`, the new
residual blocks as the identity), an exported ONNX file made trainable again
(`state_from_onnx`), or a pretrained backbone with its first blocks frozen (`frozen_modules`);
and the float16 weights file that `--init-from` starts from (`write_weights`).
"""
import numpy as np

from handmocap.perception.crops import CROP


def write_weights(path, net, refine, backbone, iteration, history=(), **meta):
    """Save `net`'s weights in float16 (half the size; `handtrain detnet --init-from` casts
    them back) with what a run needs to go on from them (its shape: net.arch()), and say so.
    meta: more fields."""
    import torch
    half = {k: v.half() if v.is_floating_point() else v for k, v in net.state_dict().items()}
    torch.save({"model": half, "iteration": iteration, "refine": refine, "backbone": backbone, **net.arch(),
                "history": list(history), **meta}, path)
    options = "".join(f" --{k.replace('_', '-')}" + ("" if v is True else f" {v}")
                      for k, v in net.arch().items() if v and k != "fine")
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB): "
          f"`handtrain detnet --backbone {backbone}{options} --init-from {path}` trains on from it")


def load_matching(net, state):
    """Load the tensors of `state` whose name and shape match `net`; -> the module names left fresh."""
    own = net.state_dict()
    keep = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    net.load_state_dict(keep, strict=False)
    return {k.rsplit(".", 2)[0] for k in own if k not in keep}


def unpadded(w, shape):
    """The exported conv weight `w` as DetNet's `shape`: itself, or with the zero channels that
    onnx_models.pad_depthwise_convs appended (output or input channels) cut off; None when
    it is neither."""
    if tuple(w.shape) == tuple(shape):
        return w
    if w.dim() != len(shape) or any(a < b for a, b in zip(w.shape, shape)) or w.shape[2:] != shape[2:]:
        return None
    rest = w.clone()
    rest[:shape[0], :shape[1]] = 0
    return w[:shape[0], :shape[1]] if not rest.any() else None


def onnx_doc(model):
    """An exported DetNet's doc string as {key: value} ("backbone", detnet.ARCH's parts, "refine")."""
    return dict(p.split("=", 1) for p in model.doc_string.split() if "=" in p)


def recorded_parts(source):
    """{part: its value (False where it has none, else True or its kind, e.g. "slim")} for each of
    detnet.PARTS, from a loaded checkpoint (dict) or the path of an exported file."""
    from handmocap.training.detnet import PARTS, part_value
    if isinstance(source, dict):
        return {k: source.get(k) or False for k in PARTS}
    import onnx
    doc = onnx_doc(onnx.load(str(source), load_external_data=False))
    return {k: part_value(doc.get(k)) for k in PARTS}


def state_from_onnx(path, images):
    """A trainable `DetNet` state dict recovered from an exported ONNX file (`path`), so the
    shipped model can seed training on a machine without its checkpoint.

    The export folds each BatchNorm into the convolution before it (W' = W*g/s, b' = b - m*g/s),
    so the file holds only the folded function. Each conv gets W' back and its BN is set up
    again around the statistics of W'x on `images` (N,128,128,3) uint8: with m and v the
    per-channel mean and variance there, BN(m, v, gamma=sqrt(v+eps), beta=b'+m) computes
    exactly W'x + b' in eval mode, and nearly so with batch statistics in training, so
    training goes on from the exported function. -> (state dict, backbone name).
    """
    import onnx
    import torch
    from onnx import numpy_helper

    from handmocap.training.detnet import ARCH, DetNet, part_value
    model = onnx.load(str(path))
    doc = onnx_doc(model)
    backbone = doc.get("backbone", "fast")
    arch = {k: part_value(doc.get(k)) for k in ARCH}
    params = {t.name: torch.from_numpy(numpy_helper.to_array(t).copy()) for t in model.graph.initializer}
    for node in model.graph.node:       # the exporter shares equal tensors (e.g. untrained biases) via Identity
        if node.op_type == "Identity" and node.input[0] in params:
            params[node.output[0]] = params[node.input[0]]
    net = DetNet(backbone, **arch).eval()
    called = []                                         # convs in the order the forward pass calls them
    hooks = [m.register_forward_hook(lambda m, i, o: called.append(m))
             for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        net(torch.zeros(1, 3, CROP, CROP))
    for h in hooks:
        h.remove()
    convs = [n for n in model.graph.node if n.op_type == "Conv"]          # the graph keeps the call order
    if len(convs) != len(called):
        raise ValueError(f"{path}: {len(convs)} convolutions, a {backbone} DetNet has {len(called)}")
    bn_after = {seq[k]: seq[k + 1] for seq in net.modules() if isinstance(seq, torch.nn.Sequential)
                for k in range(len(seq) - 1) if isinstance(seq[k + 1], torch.nn.BatchNorm2d)}
    folded_bias = {}
    with torch.no_grad():
        for conv, node in zip(called, convs):
            w = unpadded(params[node.input[1]], conv.weight.shape)
            if w is None:
                raise ValueError(f"{path}: conv weight {tuple(params[node.input[1]].shape)} where DetNet has "
                                 f"{tuple(conv.weight.shape)}")
            conv.weight.copy_(w)
            b = params[node.input[2]][:w.shape[0]] if len(node.input) > 2 else torch.zeros(w.shape[0])
            if conv in bn_after:                        # an identity BN + b' until its statistics are known
                bn = bn_after[conv]
                folded_bias[bn] = b
                bn.weight.fill_(1.0), bn.bias.copy_(b), bn.running_mean.zero_(), bn.running_var.fill_(1.0 - bn.eps)
            else:
                conv.bias.copy_(b)
        for name, p in net.named_parameters():          # the linear heads keep their names
            if f"net.{name}" in params:
                p.copy_(params[f"net.{name}"])
        stats = {}                                      # BN -> its input W'x on `images` (the exported function's)
        hooks = [bn.register_forward_hook(lambda m, i, o: stats.__setitem__(m, i[0])) for bn in folded_bias]
        x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0
        net(x)
        for h in hooks:
            h.remove()
        for bn, b in folded_bias.items():
            mean, var = stats[bn].mean((0, 2, 3)), stats[bn].var((0, 2, 3), unbiased=False)
            bn.running_mean.copy_(mean), bn.running_var.copy_(var)
            bn.weight.copy_(torch.sqrt(var + bn.eps)), bn.bias.copy_(b + mean)
    return net.state_dict(), backbone


def frozen_modules(net, k):
    """A pretrained backbone's stem and first k blocks (`net.backbone.trunk`), which keep their
    ImageNet weights and BN statistics: [modules]."""
    trunk = net.backbone.trunk
    return [trunk._conv_stem, trunk._bn0, *trunk._blocks[:k]] if k > 0 else []


def identity_init_new_blocks(net, state):
    """Residual blocks of `net` that checkpoint `state` lacks get their last BN scale zeroed:
    each adds nothing at first, so the grown net computes what the loaded one did and
    training starts from there. -> their names."""
    from handmocap.training.detnet import InvertedResidual
    names = []
    for name, m in net.named_modules():
        if isinstance(m, InvertedResidual) and m.residual and f"{name}.body.2.1.weight" not in state:
            m.body[2][1].weight.data.zero_()
            names.append(name)
    return names
