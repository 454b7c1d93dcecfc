"""The hand finder's training data: turned frames keep their boxes on the hand."""
import numpy as np

from handmocap.perception.hand_finder import INPUT_SIZE
from handmocap.training.train_finder import augment, rotate90, targets


def drawn_box(image):
    ys, xs = np.nonzero(image[..., 0] > 64)
    return np.array([xs.min(), ys.min(), xs.max(), ys.max()], float)


def test_a_turned_frame_keeps_its_box_on_the_drawn_hand():
    image = np.zeros((160, 160, 3), np.uint8)
    image[30:71, 100:141] = 255                       # rows 30..70, columns 100..140
    boxes = np.array([[100.0, 30.0, 140.0, 70.0], [np.nan] * 4])
    for k in range(4):
        turned, b = rotate90(image, boxes, k)
        np.testing.assert_array_equal(b[0], drawn_box(turned))
        assert np.isnan(b[1]).all()
    assert not np.array_equal(rotate90(image, boxes, 1)[1][0], boxes[0])   # a turn moves it


def test_augment_with_turns_keeps_boxes_on_the_hand_and_turns_some_frames():
    image = np.zeros((224, 224, 3), np.uint8)
    image[20:80, 140:180] = 255                        # a tall box in the upper right
    boxes = np.array([[140.0, 20.0, 179.0, 79.0], [np.nan] * 4])
    rng = np.random.default_rng(0)
    tall = wide = 0
    for _ in range(40):
        out, b, right = augment(rng, image, boxes, np.array([True, False]), zoom=(0.9, 1.0), rot90=0.5)
        assert out.shape == (INPUT_SIZE, INPUT_SIZE, 3)
        np.testing.assert_allclose(b[0], drawn_box(out), atol=2.0)
        w, h = b[0, 2] - b[0, 0], b[0, 3] - b[0, 1]
        tall, wide = tall + (h > w), wide + (w > h)
        heat, reg, mask = targets(b, right)
        assert mask.sum() == 1
    assert tall > 5 and wide > 5                       # upright and quarter-turned frames both came


def test_grey_frames_are_luma_in_three_equal_channels_and_only_the_asked_share_is_grey():
    from handmocap.perception.hand_finder import greyed
    rng = np.random.default_rng(0)
    image = np.zeros((160, 160, 3), np.uint8)
    image[30:71, 100:141] = (40, 120, 220)            # a skin-like BGR patch
    g = greyed(image[None])[0]
    assert g.shape == image.shape and (g[..., 0] == g[..., 1]).all() and (g[..., 1] == g[..., 2]).all()
    assert abs(int(g[50, 120, 0]) - round(0.114 * 40 + 0.587 * 120 + 0.299 * 220)) <= 1
    boxes = np.array([[100.0, 30.0, 140.0, 70.0], [np.nan] * 4])
    grey = [np.ptp(augment(rng, image, boxes, np.array([True, False]), zoom=(0.9, 1.0), grey=0.3)[0], axis=-1).max() == 0
            for _ in range(400)]
    assert 0.22 < np.mean(grey) < 0.38
    assert not any(np.ptp(augment(rng, image, boxes, np.array([True, False]), zoom=(0.9, 1.0))[0], axis=-1).max() == 0
                   for _ in range(50))


def test_a_larger_finder_input_round_trips_its_boxes_through_targets_and_decode():
    """handtrain finder --size S: the target maps of an S px frame, read back by the
    runtime's decode at input_size S, give the same box (the log side is in units of S)."""
    from handmocap.perception.hand_finder import STRIDE, decode
    for size in (160, 256):
        box = np.array([[90.0, 40.0, 130.0, 100.0], [np.nan] * 4])     # 40 x 60 px: side 60
        heat, reg, mask = targets(box, np.array([True, False]), size)
        assert heat.shape == (size // STRIDE, size // STRIDE)
        logit = np.log(np.clip(heat, 1e-6, 1 - 1e-6) / np.clip(1 - heat, 1e-6, 1))
        maps = np.concatenate([logit[None], reg[:3], np.where(mask > 0, 5.0, -5.0)[None]])
        (found, score, right), = decode(maps, 0.5, input_size=size)
        np.testing.assert_allclose(found, [80.0, 40.0, 140.0, 100.0], atol=1e-3)
        assert score > 0.99 and right > 0.99



def test_the_runtime_finder_letterboxes_into_its_file_s_input_side(tmp_path):
    """A finder exported at 256 px is read at 256 px (HandFinder.size), the shipped one at 160."""
    import pytest
    torch = pytest.importorskip("torch", reason="exporting a finder needs the training extra (torch)")
    from handmocap.perception.hand_finder import HandFinder
    from handmocap.training.train_finder import build_model, export
    torch.manual_seed(0)
    export(build_model(), tmp_path / "finder256.onnx", 256)
    finder = HandFinder.load(tmp_path / "finder256.onnx")
    assert finder.size == 256
    maps, lb = finder.raw(np.zeros((480, 640, 3), np.uint8))
    assert maps.shape == (5, 32, 32) and abs(lb.scale_x - 0.4) < 1e-9
    assert HandFinder.load().size == INPUT_SIZE


def test_export_only_exports_at_the_side_the_checkpoint_was_trained_at(tmp_path):
    """handtrain finder --export-only: the file's input side is the checkpoint's `size`
    (a 256 px run exported without --size must not come out as a 160 px finder)."""
    import argparse
    import pytest
    torch = pytest.importorskip("torch", reason="exporting a finder needs the training extra (torch)")
    import onnx
    from handmocap.training.train_finder import add_arguments, build_model, main
    torch.save({"model": build_model().state_dict(), "iter": 1, "size": 256}, tmp_path / "last.pt")
    p = argparse.ArgumentParser()
    add_arguments(p)
    main(p.parse_args(["--export-only", "--run-dir", str(tmp_path), "--export", str(tmp_path / "f.onnx")]))
    dims = onnx.load(str(tmp_path / "f.onnx")).graph.input[0].type.tensor_type.shape.dim
    assert [d.dim_value for d in dims[2:]] == [256, 256]


def test_a_lite0_finder_keeps_the_file_interface_and_its_checkpoint_says_its_backbone(tmp_path):
    """The lite0 finder takes what the scratch one does ((N,3,S,S) RGB in [0,1], the ImageNet
    scaling inside) and gives (N,5,S/8,S/8); its checkpoint's `backbone` makes --export-only
    build a lite0 network without being told (a scratch one could not load its weights)."""
    import argparse
    import pytest
    torch = pytest.importorskip("torch", reason="a lite0 finder needs the training extra (torch)")
    from handmocap.perception.hand_finder import HandFinder
    from handmocap.training.train_finder import add_arguments, build_model, frozen_blocks, main
    net = build_model("lite0")
    assert net(torch.rand(2, 3, 192, 192)).shape == (2, 5, 24, 24)
    assert len(frozen_blocks(net, 3)) == 5 and frozen_blocks(build_model(), 3) == []
    torch.save({"model": net.state_dict(), "iter": 1, "size": 192, "backbone": "lite0"}, tmp_path / "last.pt")
    p = argparse.ArgumentParser()
    add_arguments(p)
    main(p.parse_args(["--export-only", "--run-dir", str(tmp_path), "--export", str(tmp_path / "f.onnx")]))
    finder = HandFinder.load(tmp_path / "f.onnx")
    assert finder.size == 192 and finder.raw(np.zeros((480, 640, 3), np.uint8))[0].shape == (5, 24, 24)


def test_a_pasted_hand_graphic_covers_no_hand_box_and_adds_no_target():
    """A printed hand-like graphic is a negative: it lands off the labelled boxes (so a real
    hand is never painted over) and the frame's targets are those of its real boxes only."""
    from handmocap.training.train_finder import hand_graphic, paste_graphic
    rng = np.random.default_rng(1)
    uv = np.array([[0, 0], [-8, -6], [-14, -14], [-18, -22], [-20, -30], [-6, -24], [-7, -36], [-7, -44], [-7, -50],
                   [0, -25], [0, -38], [0, -47], [0, -54], [6, -24], [7, -36], [7, -44], [7, -50],
                   [12, -20], [14, -30], [15, -36], [16, -41]], float)
    patch, alpha = hand_graphic(rng, uv, 60)
    assert patch.shape[:2] == alpha.shape and 0.1 < (alpha > 0.5).mean() < 0.9    # a shape, not a square
    image = np.full((192, 192, 3), 90, np.uint8)
    boxes = np.array([[10.0, 10.0, 90.0, 90.0], [np.nan] * 4])
    changed = 0
    for _ in range(20):
        out = paste_graphic(rng, image, boxes, uv, side_range=(0.2, 0.3))
        assert (out[10:91, 10:91] == 90).all()                     # the hand's box untouched
        changed += (out != 90).any()
        heat, reg, mask = targets(boxes, np.array([True, False]), 192)
        assert mask.sum() == 1
    assert changed >= 15


def test_a_side_branch_keeps_the_finder_s_maps_and_starts_from_weights_without_one(tmp_path):
    """--side-branch: the side map comes from a branch of its own; the other four maps are
    the shared head's, so weights trained without the branch load (the branch starts fresh)."""
    import pytest
    torch = pytest.importorskip("torch", reason="a lite0 finder needs the training extra (torch)")
    from handmocap.training.train_finder import build_model
    plain, branched = build_model("lite0"), build_model("lite0", side_branch=True)
    missing, unexpected = branched.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("side.") for k in missing)
    plain.eval(), branched.eval()
    x = torch.rand(1, 3, 192, 192)
    with torch.no_grad():
        a, b = plain(x), branched(x)
    assert b.shape == (1, 5, 24, 24)
    torch.testing.assert_close(a[:, :4], b[:, :4])
    assert not torch.allclose(a[:, 4], b[:, 4])
