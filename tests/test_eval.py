"""PCK/AUC on hand-made cases, `handeval score` and `handeval predict` (fake networks on
dot-drawn hands; the real models on the rendered clip when they are committed)."""
import subprocess

import cv2
import numpy as np
import pytest

from conftest import ROOT, SHARED_DATA
from handmocap.training import eval_cli, metrics
from handmocap.perception.detector import HandDetector
from handmocap.training.pose_data import PoseSampler
from handmocap.perception.hand_model import HandModel
from handmocap.perception.tracker import HandTracker
from test_detector import DOT_TOL, FakeDetNet, FakeFinder, canonical_hand, draw

MODEL = HandModel.load()
T = metrics.PCK_THRESHOLDS_MM


def hands(n=10, seed=0):
    """(n,21,3) camera-frame joints in metres of sampled hands 0.5 m away."""
    d = PoseSampler(MODEL).sample(n, np.random.default_rng(seed))
    _, joints = MODEL.forward(d["quats"], d["beta"])
    return joints - joints[:, 9:10] + np.array([0.0, 0.0, 0.5])


def test_perfect_prediction_has_auc_one_whatever_its_scale_and_position():
    gt = hands()
    s = metrics.score_3d(gt, gt)
    assert s["auc"] == pytest.approx(1.0) and s["mean_mm"] == pytest.approx(0.0, abs=1e-9)
    moved = (gt - gt[:, 9:10]) * 3.0 + np.array([0.2, -0.1, 1.0])     # other scale and place: aligned away
    assert metrics.score_3d(moved, gt)["auc"] == pytest.approx(1.0)


def test_one_joint_off_by_a_known_distance_gives_the_known_pck():
    gt = hands()
    pred = gt.copy()
    pred[:, 8] += np.array([0.036, 0.0, 0.0])          # index tip 36 mm off; root and wrist untouched
    s = metrics.score_3d(pred, gt)
    want = np.where(T < 36.0, 20 / 21, 1.0)
    np.testing.assert_allclose(s["pck"], want)
    assert s["auc"] == pytest.approx(metrics.auc(T, want))
    assert s["mean_mm"] == pytest.approx(36.0 / 21)
    assert 20 / 21 < s["auc"] < 1.0


def test_missing_hands_count_as_misses_and_missing_ground_truth_is_left_out():
    gt = hands(4)
    pred = gt.copy()
    pred[:2] = np.nan                                  # two hands not found
    assert metrics.score_3d(pred, gt)["auc"] == pytest.approx(0.5)
    valid = np.ones((4, 21), bool)
    valid[:2] = False                                  # ... but they have no ground truth
    assert metrics.score_3d(pred, gt, valid)["auc"] == pytest.approx(1.0)


def test_auc_is_the_normalized_trapezoid():
    assert metrics.auc([0, 1, 2], [0.0, 1.0, 1.0]) == pytest.approx(0.75)


def test_a_skeleton_rebuilt_on_other_proportions_keeps_its_bone_directions_and_costs_auc():
    gt = hands()
    ratio = metrics.bone_per_reference(gt)
    assert ratio.shape == (10, 21) and np.allclose(ratio[:, 9], 1.0) and np.all(ratio[:, 0] == 0.0)
    same = metrics.with_proportions(gt, ratio[0])      # every hand on the first one's proportions
    np.testing.assert_allclose(metrics.with_proportions(gt[:1], ratio[0]), gt[:1], atol=1e-12)   # its own: unchanged
    longer = ratio[0].copy()
    longer[[6, 10, 14, 18]] *= 1.5                     # proximal finger bones half as long again
    moved = metrics.with_proportions(gt, longer)
    np.testing.assert_allclose(metrics.bone_per_reference(moved)[:, 1:], np.broadcast_to(longer[1:], (10, 20)),
                               rtol=1e-9)
    bone = lambda x, j, p: (x[:, j] - x[:, p]) / np.linalg.norm(x[:, j] - x[:, p], axis=-1, keepdims=True)  # noqa: E731
    np.testing.assert_allclose(bone(moved, 7, 6), bone(gt, 7, 6), atol=1e-12)
    np.testing.assert_allclose(moved[:, 0], gt[:, 0])
    assert metrics.score_3d(moved, gt)["auc"] < metrics.score_3d(same, gt)["auc"] <= 1.0


def test_2d_offsets():
    gt = np.random.default_rng(0).uniform(0, 300, (5, 21, 2))
    s = metrics.score_2d(gt + np.array([3.0, 4.0]), gt)
    assert s["mean_px"] == pytest.approx(5.0) and s["median_px"] == pytest.approx(5.0)
    np.testing.assert_allclose(s["pck"], (s["thresholds_px"] >= 5.0 - 1e-9).astype(float))


def test_score_picks_the_hand_nearest_the_ground_truth_and_writes_the_curve(tmp_path, capsys):
    gt_xyz = hands(3)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    gt_uv = eval_cli.project(K, gt_xyz)
    pred = eval_cli.empty_prediction(3)
    for i in range(3):       # the top hand is elsewhere; the second one is the labelled hand
        eval_cli.put_hands(pred, i, [
            {"xyz": gt_xyz[i] + 0.3, "xyz_rel": gt_xyz[i], "uv": gt_uv[i] + 200, "handedness": "left", "score": 0.9},
            {"xyz": gt_xyz[i], "xyz_rel": gt_xyz[i], "uv": gt_uv[i], "handedness": "right", "score": 0.8}])
    np.savez(tmp_path / "pred.npz", **pred)
    np.savez(tmp_path / "gt.npz", uv=gt_uv, xyz=gt_xyz)
    png = tmp_path / "curve.png"
    assert eval_cli.main(["score", "--pred", str(tmp_path / "pred.npz"), "--gt", str(tmp_path / "gt.npz"),
                          "--png", str(png), "--json", str(tmp_path / "s.json")]) == 0
    out = capsys.readouterr().out
    assert "found 100.0%" in out and "2D mean 0.0 px" in out and "DetNet+IKNet+FK 3D AUC 20-50mm 1.000" in out
    assert cv2.imread(str(png)) is not None


def dot_images(folder, n=4):
    """Dot-hand images, the second one without a hand."""
    folder.mkdir()
    truth = []
    for i in range(n):
        img = np.zeros((480, 640, 3), np.uint8)
        uv = canonical_hand((260 + 20 * i, 300), 150)
        if i != 1:
            draw(img, uv)
        cv2.imwrite(str(folder / f"{i:03d}.png"), img)
        truth.append(uv)
    return np.array(truth)


def check_prediction_file(path, n):
    with np.load(path) as p:
        assert p["xyz"].shape == (n, 21, 3) and p["xyz_rel"].shape == (n, 21, 3) and p["uv"].shape == (n, 21, 2)
        assert p["found"].shape == (n,) and p["found"].dtype == bool and p["handedness"].shape == (n,)
        assert p["handedness"].dtype.kind == "U"
        for i in range(n):
            assert np.isfinite(p["xyz"][i]).all() == p["found"][i] == np.isfinite(p["uv"][i]).all()
            assert (p["handedness"][i] in ("left", "right")) == p["found"][i]
        return {k: p[k] for k in p.files}


@pytest.mark.skipif(not (ROOT / "models" / "iknet.onnx").is_file(), reason="models/iknet.onnx not present")
def test_predict_writes_the_documented_arrays(tmp_path):
    truth = dot_images(tmp_path / "imgs")
    tracker = HandTracker(detector=HandDetector(FakeDetNet(), FakeFinder()), smooth=False)
    K = eval_cli.parse_K("500,500,319.5,239.5", None, 4)
    eval_cli.predict(tmp_path / "imgs", K, tmp_path / "pred.npz", tracker=tracker)
    p = check_prediction_file(tmp_path / "pred.npz", 4)
    assert p["found"].tolist() == [True, False, True, True]
    np.testing.assert_allclose(p["uv"][[0, 2, 3]], np.round(truth[[0, 2, 3]]), atol=DOT_TOL)


@pytest.mark.skipif(not (ROOT / "models" / "iknet.onnx").is_file(), reason="models/iknet.onnx not present")
def test_an_unreadable_photo_is_reported_and_the_others_are_predicted(tmp_path):
    truth = dot_images(tmp_path / "imgs")
    (tmp_path / "imgs" / "002.png").write_bytes(b"\x89PNG\r\n\x1a\n not a png")   # replaces a hand image
    lines = []
    tracker = HandTracker(detector=HandDetector(FakeDetNet(), FakeFinder()), smooth=False)
    eval_cli.predict(tmp_path / "imgs", None, tmp_path / "pred.npz", tracker=tracker, log=lines.append)
    p = check_prediction_file(tmp_path / "pred.npz", 4)
    assert p["names"].tolist() == ["000.png", "001.png", "002.png", "003.png"]
    assert p["unreadable"].tolist() == [False, False, True, False]
    assert p["found"].tolist() == [True, False, False, True]
    np.testing.assert_allclose(p["uv"][[0, 3]], np.round(truth[[0, 3]]), atol=DOT_TOL)
    assert any("002.png: cannot be decoded" in line for line in lines)
    assert "4 images (1 unreadable)" in lines[-1]


DETNET, FINDER = ROOT / "models" / "detnet.onnx", ROOT / "models" / "finder.onnx"


@pytest.mark.skipif(not (DETNET.is_file() and FINDER.is_file()), reason="models/detnet.onnx or finder.onnx not committed yet")
def test_handeval_predict_cli_on_rendered_images(tmp_path):
    cap = cv2.VideoCapture(str(ROOT / "data" / "demo" / "hand_clip.mp4"))
    (tmp_path / "imgs").mkdir()
    for i in range(6):
        ok, frame = cap.read()
        cv2.imwrite(str(tmp_path / "imgs" / f"{i:03d}.png"), frame)
    K = np.load(ROOT / "data" / "demo" / "hand_clip.npz")["K"]
    np.save(tmp_path / "K.npy", K)
    assert eval_cli.main(["predict", "--images", str(tmp_path / "imgs"), "--K-file", str(tmp_path / "K.npy"),
                          "--out", str(tmp_path / "pred.npz")]) == 0
    p = check_prediction_file(tmp_path / "pred.npz", 6)
    assert p["found"].sum() >= 5


def test_bad_K_is_an_error_not_a_crash(tmp_path, capsys):
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.zeros((8, 8, 3), np.uint8))
    np.save(tmp_path / "K.npy", np.ones((3, 4)))
    assert eval_cli.main(["predict", "--images", str(tmp_path / "imgs"), "--K-file", str(tmp_path / "K.npy"),
                          "--out", str(tmp_path / "p.npz")]) == 2
    assert "K.npy" in capsys.readouterr().err


def test_set_passes_detector_settings_and_refuses_unknown_ones(tmp_path, capsys):
    assert eval_cli.detector_settings(["tracked_test_time_crops=4", "evict_margin=null", "crop_scale=1.4"]) == \
        {"tracked_test_time_crops": 4, "evict_margin": None, "crop_scale": 1.4}
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.zeros((8, 8, 3), np.uint8))
    args = ["predict", "--images", str(tmp_path / "imgs"), "--out", str(tmp_path / "p.npz"), "--set"]
    assert eval_cli.main(args + ["tracked_test_time_crop=4"]) == 2
    assert "--set tracked_test_time_crop=4" in capsys.readouterr().err
    assert eval_cli.main(args + ["test_time_crops=2"]) == 0         # overrides the photo settings' 4


@pytest.mark.skipif(not (SHARED_DATA / "samples" / "mmpose" / "rhd").is_dir(), reason="no shared/data pack beside the repository")
def test_split_ground_truth_reprojects(tmp_path):
    """The RHD and InterHand samples' 3D projects onto their 2D labels (joint orders right)."""
    import json
    eval_cli.build_rhd(SHARED_DATA, tmp_path / "rhd")
    gt = np.load(tmp_path / "rhd" / "gt.npz")
    doc = json.loads((SHARED_DATA / "samples/mmpose/rhd/test_rhd.json").read_text())
    kp = np.array([np.asarray(a["keypoints"])[eval_cli.RHD_TO_MP, :2] for a in doc["annotations"]])
    np.testing.assert_allclose(gt["uv"], kp, atol=0.2)
    # MP order: the wrist -> middle MCP bone is the palm's length (7-11 cm)
    bone = np.linalg.norm(gt["xyz"][:, 0] - gt["xyz"][:, 9], axis=-1)
    assert np.all((0.06 < bone) & (bone < 0.12)), bone
    eval_cli.build_interhand(SHARED_DATA, tmp_path / "ih")
    ih = np.load(tmp_path / "ih" / "gt.npz")
    bone = np.linalg.norm(ih["xyz"][:, 0] - ih["xyz"][:, 9], axis=-1)
    assert np.all((0.06 < bone) & (bone < 0.12)), bone


def test_the_iknet_option_names_the_file_that_runs_by_default(capsys):
    """handeval's --iknet help once named models/iknet.onnx while the int8 copy runs by default."""
    from handmocap.perception.ik_solver import DEFAULT_MODEL
    with pytest.raises(SystemExit):
        eval_cli.main(["predict", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert f"int8 (default, models/{DEFAULT_MODEL.name})" in help_text


def test_score_tells_what_the_hands_read_as_the_wrong_side_cost():
    """Two hands read as their labelled side 2 px off, one read as the wrong side 10 px off:
    the wrong side's mean error, the others', and the ratio in the summary line."""
    gt_uv = np.random.default_rng(1).uniform(50, 250, (3, 21, 2))
    pred = eval_cli.empty_prediction(3)
    for i, (side, off) in enumerate((("right", 2.0), ("right", 2.0), ("left", 10.0))):
        eval_cli.put_hands(pred, i, [{"xyz": np.zeros((21, 3)), "xyz_rel": np.zeros((21, 3)),
                                      "uv": gt_uv[i] + [off, 0.0], "handedness": side, "score": 0.9}])
    s = eval_cli.score(pred, {"uv": gt_uv, "handedness": np.array(["right"] * 3)})
    assert s["handedness_acc"] == pytest.approx(2 / 3) and s["wrong_side_hands"] == 1
    assert s["right_side_px"] == pytest.approx(2.0) and s["wrong_side_px"] == pytest.approx(10.0)
    assert "the 1 read as the wrong side 10.0 px, 5.00x the others' 2.0" in eval_cli.summary_line("x", s)
    every = eval_cli.score(pred, {"uv": gt_uv, "handedness": np.array(["right", "right", "left"])})
    assert every["wrong_side_hands"] == 0 and "wrong_side_px" not in every


def test_the_mediapipe_reference_venv_is_found_or_built_or_said_absent(tmp_path, monkeypatch, capsys):
    """bench_tracker and handeval splits need MediaPipe in a venv of its own: an existing one
    is used; an absent default one is built (a venv, then pip install of the pin: here a small
    package stands in for mediapipe); one named by HANDMOCAP_MEDIAPIPE_PYTHON that is absent is
    one line, no build."""
    import sys
    from pathlib import Path

    from handmocap.training import eval_cli
    monkeypatch.setattr(eval_cli, "REFERENCE_PYTHON", Path(sys.executable))
    assert eval_cli.reference_python() == Path(sys.executable)
    target = tmp_path / "mpenv" / "bin" / "python"
    monkeypatch.setattr(eval_cli, "REFERENCE_PYTHON", target)
    monkeypatch.setenv("HANDMOCAP_MEDIAPIPE_PYTHON", str(target))
    assert eval_cli.reference_python() is None and "absent" in capsys.readouterr().out and not target.exists()
    monkeypatch.delenv("HANDMOCAP_MEDIAPIPE_PYTHON")
    monkeypatch.setattr(eval_cli, "MEDIAPIPE_PIN", "six")
    assert eval_cli.reference_python() == target and target.is_file()
    assert "building" in capsys.readouterr().out
    assert subprocess.run([str(target), "-c", "import six"]).returncode == 0


def test_detector_keywords_are_what_handdetector_load_takes():
    """handeval's model arguments reach HandDetector.load under its own keyword names (the
    tracker's), without iknet and the ones not given."""
    import inspect

    from handmocap.perception.detector import HandDetector
    kw = eval_cli.detector_keywords({"detnet": "a.onnx", "side_detnet": None, "finder": "f.onnx", "iknet": "i.onnx",
                                     "max_hands": 1})
    assert kw == {"detnet": "a.onnx", "finder": "f.onnx", "max_hands": 1}
    params = inspect.signature(HandDetector.load).parameters
    assert all(k in params for k in kw if k != "max_hands")
