"""Real data loaders (shared/data) and the crop geometry; data tests skip without shared/."""
import numpy as np
import pytest

from handmocap.training import real_data
from handmocap.training.real_data import SHARED_DATA

needs_data = pytest.mark.skipif(not (SHARED_DATA / "labelled2d").exists(),
                                reason=f"no real data pack at {SHARED_DATA}")


def test_joint_order_tables_are_permutations():
    assert sorted(real_data.RHD_TO_MP) == list(range(21))
    assert real_data.RHD_TO_MP[4] == 1 and real_data.RHD_TO_MP[1] == 4          # thumb tip..base reversed
    for offset in (0, 21):
        idx = real_data.interhand_to_mp(offset)
        assert sorted(idx) == list(range(offset, offset + 21))
        assert idx[0] == offset + 20                                             # wrist last in InterHand


def test_crop_affine_maps_box_centre_and_mirrors():
    M = real_data.crop_affine(200.0, 100.0, 64.0, 128)
    assert np.allclose(real_data.apply_affine(M, np.array([200.0, 100.0])), 63.5)
    assert np.allclose(real_data.apply_affine(M, np.array([232.0, 100.0])), [127.5, 63.5])
    Mm = real_data.crop_affine(200.0, 100.0, 64.0, 128, mirror=True)
    assert np.allclose(real_data.apply_affine(Mm, np.array([232.0, 100.0])), [-0.5, 63.5])
    Mr = real_data.crop_affine(200.0, 100.0, 64.0, 128, angle_deg=90.0)
    assert np.allclose(real_data.apply_affine(Mr, np.array([232.0, 100.0])), [63.5, -0.5], atol=1e-9)


@needs_data
def test_howiema_subjects_are_disjoint_and_labelled():
    train = real_data.load_howiema("001")
    held = real_data.load_howiema("040")
    assert len(train) > 400 and len(held) > 400
    assert {s["name"].split("/")[0] for s in train} == {"001"}
    s = train[0]
    assert s["image"].shape == (256, 256, 3) and s["uv"].shape == (21, 2)
    assert np.all((s["uv"] >= 0) & (s["uv"] < 256))
    assert {x["handedness"] for x in train} == {"left", "right"}


@needs_data
def test_mmpose_3d_sets_reproject_to_their_2d():
    for name in ("rhd", "interhand2.6m"):
        samples = real_data.load_mmpose(name)
        assert samples
        for s in samples:
            p = s["xyz"] @ s["K"].T
            uv = p[:, :2] / p[:, 2:]
            assert np.abs(uv - s["uv"])[s["visible"]].max() < 0.5
            bone = np.linalg.norm(s["xyz"][0] - s["xyz"][9])
            assert 0.05 < bone < 0.15                                     # wrist -> middle MCP in metres


@needs_data
def test_2d_sample_sets_load():
    for name, count in (("freihand", 8), ("panoptic", 4), ("onehand10k", 4)):
        samples = real_data.load_mmpose(name)
        assert len(samples) == count
        for s in samples:
            h, w = s["image"].shape[:2]
            vis = s["uv"][s["visible"]]
            assert np.all((vis >= 0) & (vis <= [w, h]))
    cmu = real_data.load_cmu_hand_labels_sample()
    assert len(cmu) == 16 and cmu[0]["image"].shape == (368, 368, 3)


@needs_data
def test_temugeb_triangulation_projects_near_mediapipe():
    cv2 = pytest.importorskip("cv2")
    samples = real_data.load_temugeb_stereo(every=90)
    assert samples and samples[0]["image"].shape == (720, 720, 3)
    for s in samples:
        uv, _ = cv2.projectPoints(s["xyz"].astype(np.float64), np.zeros(3), np.zeros(3),
                                  s["K"].astype(np.float64), s["dist"].astype(np.float64))
        assert np.median(np.linalg.norm(uv[:, 0] - s["uv"], axis=-1)) < 6.0


@needs_data
def test_training_videos_exclude_evaluation_splits():
    assert not any("temugeb" in v for v in real_data.TRAIN_VIDEOS)
    for v in real_data.TRAIN_VIDEOS:
        labels = real_data.load_pseudo_labels(SHARED_DATA / v)
        assert labels["uv"].shape[1:] == (2, 21, 2)
