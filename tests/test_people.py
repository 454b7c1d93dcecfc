"""People never trained on: the pseudo-label filter, the held-back split, and the scoring of
`handeval people` (handmocap/training/eval_people.py)."""
import numpy as np
import pytest

from conftest import DEMO_CLIP, DEMO_TRUTH, SHARED_DATA
from handmocap.training import eval_people, real_data

needs_wild = pytest.mark.skipif(not (SHARED_DATA / "video" / "wild").is_dir(),
                                reason="the data pack's second drop (shared/data/video/wild) is not beside the repo")


def hand(cx, cy, size=100.0):
    """(21,2) joints spread over a box of `size` px centred at (cx, cy)."""
    t = np.linspace(-0.5, 0.5, 21)
    return np.stack([cx + size * t, cy + size * t[::-1] ** 2], -1).astype(np.float32)


def labels(frames):
    """Pseudo-label arrays of a clip from [[(uv (21,2), side 0 right / 1 left), ...] per frame]."""
    n = len(frames)
    lab = {"uv": np.zeros((n, 2, 21, 2), np.float32), "found": np.zeros((n, 2), bool),
           "handedness": np.full((n, 2), -1, np.int8)}
    for f, hands in enumerate(frames):
        for s, (uv, side) in enumerate(hands):
            lab["uv"][f, s], lab["found"][f, s], lab["handedness"][f, s] = uv, True, side
    return lab


def test_a_steady_hand_is_kept_and_a_flicker_dropped():
    # frames 0-4: a right hand moving 5 px a frame; frame 2 also a left "hand" far away that
    # is there in no other frame (a misread), frame 4 the right hand jumps by 2 hand sizes
    steady = [[(hand(100 + 5 * f, 100), 0)] for f in range(4)] + [[(hand(320, 100), 0)]]
    steady[2].append((hand(400, 300), 1))
    ok = real_data.reliable_hands(labels(steady))
    assert ok[:4, 0].all()
    assert not ok[2, 1]                  # the flicker
    assert not ok[4, 0]                  # the jump: neither neighbour is near it


def test_one_hand_found_twice_two_hands_of_one_side_and_tiny_hands_are_dropped():
    twice = [[(hand(100, 100), 0), (hand(105, 102), 1)]] * 3            # overlapping: one hand found twice
    same_side = [[(hand(100, 100), 0), (hand(400, 100), 0)]] * 3         # two hands, both called right
    tiny = [[(hand(100, 100, size=10), 0)]] * 3
    pair = [[(hand(100, 100), 0), (hand(400, 100), 1)]] * 3              # two hands, two sides: kept
    for frames, kept in ((twice, False), (same_side, False), (tiny, False), (pair, True)):
        ok = real_data.reliable_hands(labels(frames))
        found = labels(frames)["found"]
        assert ok[found].all() == kept and ok[found].any() == kept


def test_photos_skip_the_test_over_time():
    lab = labels([[(hand(100, 100), 0)], [], [(hand(400, 300), 1)]])
    assert not real_data.reliable_hands(lab)[lab["found"]].any()                 # as a clip: no neighbours
    assert real_data.reliable_hands(lab, video=False)[lab["found"]].all()       # as photos: each on its own


@needs_wild
def test_held_back_people_are_in_no_training_set():
    train = {p.stem for p in real_data.wild_clips(SHARED_DATA)}
    held = {p.stem for p in real_data.wild_clips(SHARED_DATA, held_back=True)}
    assert held == set(real_data.WILD_HELD_BACK) and not train & held
    assert len(train) >= 15
    if (SHARED_DATA / "video" / "wild3").is_dir():   # the third drop: held back by person too
        both = real_data.WILD_DROPS
        train3 = {p.stem for p in real_data.wild_clips(SHARED_DATA, drops=both)} - train
        held3 = {p.stem for p in real_data.wild_clips(SHARED_DATA, held_back=True, drops=both)} - held
        assert held3 == set(real_data.WILD3_HELD_BACK) and not train3 & held3 and len(train3) >= 8
        # one person, one side: the pianist, the ASL signer and the washer are wholly held back
        people = lambda stems, prefix: {s for s in stems if s.startswith(prefix)}  # noqa: E731
        assert not people(train3, "hmj6589") and not people(train3, "limchaesung")
        assert {"AlpYksl__YES", "AlpYksl__again"} <= held3
        assert set(real_data.HELD_BACK_SCENES) == held | held3
    train_ids = {s["name"].split("/")[0] for s in real_data.load_11khands(SHARED_DATA)}
    held_ids = {s["name"].split("/")[0] for s in real_data.load_11khands(SHARED_DATA, held_back=True)}
    assert held_ids <= set(real_data.ELEVEN_K_HELD_BACK) and not train_ids & held_ids
    assert len(held_ids) >= 30 and len(train_ids) >= 120



@pytest.mark.skipif(not (SHARED_DATA / "video" / "wild3").is_dir(), reason="needs the data pack's video/wild3 (../shared)")
def test_a_later_drop_is_cut_into_a_cache_of_its_own_held_back_by_person(tmp_path):
    """build_drop_cache: the third drop's training people train (source wild/<clip>, with
    negatives), its held-back people are validation only (heldback/wild3/<clip>) and stay
    out of the held-back clips' figures of the second drop (detnet_eval.heldout_groups)."""
    from handmocap.training.detnet_data import WILD_SOURCE, build_drop_cache
    from handmocap.training.detnet_eval import heldout_groups
    cut = build_drop_cache(SHARED_DATA, tmp_path / "wild3.npz", "wild3", log=lambda *a: None)
    assert (tmp_path / "wild3.npz").is_file()
    source = cut["source"].astype(str)
    clip = np.array([s.rsplit("/", 1)[-1] for s in source])
    held_back = np.isin(clip, real_data.WILD3_HELD_BACK)
    assert held_back.any() and (~held_back).any()
    assert (cut["held"] == held_back).all()                                  # a clip is all held out or all training
    assert all(s.startswith("heldback/wild3/") for s in source[held_back])
    assert all(s.startswith(WILD_SOURCE) for s in source[~held_back])
    assert len(cut["neg"]) and not cut["neg_held"].any()                     # negatives from the training people only
    groups = heldout_groups(source)
    assert (groups["held-back clips, third drop"] == held_back).all() and not groups["held-back clips"].any()

def test_scoring_counts_found_false_and_wrong_sides():
    """score_frames with the real detector on the rendered demo clip, labelled with its
    ground truth as the right hand (found, scored), and again with a second, made-up label
    far away (never found) and the side swapped (all wrong)."""
    import cv2

    from handmocap.perception.detector import HandDetector
    truth = np.load(DEMO_TRUTH)
    cap = cv2.VideoCapture(str(DEMO_CLIP))
    frames = []
    for i in range(0, 30):
        ok, bgr = cap.read()
        frames.append((bgr, truth["uv"][i][None], np.ones(1, bool), [str(truth["handedness"])]))
    det = HandDetector.load()
    s = eval_people.score_frames(det, frames)
    m = eval_people.summary(s)
    assert m["found"] >= 0.9 and m["false_per_frame"] == 0.0
    # each scored hand keeps the detector's joint confidences and presence
    assert s["confidence"].shape == (len(s["err"]), 21) and np.all((s["confidence"] >= 0) & (s["confidence"] <= 1))
    assert s["presence"].shape == (len(s["err"]),) and np.all((s["presence"] >= 0) & (s["presence"] <= 1))
    assert m["median_err"] < 0.15 and 0.5 < m["pck"] <= 1.0
    assert m["side"] == 1.0 and np.isnan(m["wrong_side_ratio"])
    other = {"right": "left", "left": "right"}[str(truth["handedness"])]
    far = [(bgr, np.stack([uv[0], uv[0] + 400.0]), np.ones(2, bool), [other, other]) for bgr, uv, _, _ in frames]
    m2 = eval_people.summary(eval_people.score_frames(det, far))
    assert m2["labelled"] == 60 and m2["found"] <= 0.5 + 1e-9
    assert m2["side"] == 0.0 and m2["median_err"] == pytest.approx(m["median_err"], rel=0.2)


def test_merge_and_summary_arithmetic():
    a = {"frames": 2, "labelled": 3, "found": 2, "false": 1, "err": np.array([0.1, 0.3]),
         "joint_err": np.full((2, 21), 0.05), "right_side": np.array([True, False]),
         "confidence": np.full((2, 21), 0.6), "presence": np.ones(2)}
    b = {"frames": 2, "labelled": 1, "found": 1, "false": 0, "err": np.array([0.1]),
         "joint_err": np.full((1, 21), 0.2), "right_side": np.array([True]),
         "confidence": np.full((1, 21), 0.3), "presence": np.array([0.9])}
    merged = eval_people.merge([a, b])
    assert merged["confidence"].shape == (3, 21) and merged["presence"].tolist() == [1.0, 1.0, 0.9]
    m = eval_people.summary(merged)
    assert m["found"] == 0.75 and m["false_per_frame"] == 0.25 and m["scored"] == 3
    assert m["pck"] == pytest.approx(2 / 3) and m["side"] == pytest.approx(2 / 3)
    assert m["wrong_side_ratio"] == pytest.approx(0.3 / 0.1)


def test_false_hands_where_mediapipe_found_both_hands_are_counted_apart():
    """false_sure: of the false hands, those in frames where MediaPipe found two hands (no
    hand of the person is left for an output on neither), over those frames; a false hand
    beside one label may be the hand MediaPipe missed and counts in false_per_frame only."""
    right, left, far = hand(100, 100), hand(300, 100), hand(500, 400)
    out = lambda uv, tid: {"track_id": tid, "uv": uv, "handedness": "right"}   # noqa: E731
    frames = [([out(right, 0), out(left, 1), out(far, 2)], np.stack([right, left]), np.ones(2, bool), ["right"] * 2),
              ([out(right, 0), out(left, 1)], np.stack([right]), np.ones(1, bool), ["right"]),
              ([out(right, 0)], np.stack([right, left]), np.ones(2, bool), ["right"] * 2)]
    m = eval_people.summary(eval_people.score_outputs(frames))
    assert m["false_per_frame"] == pytest.approx(2 / 3) and m["false_sure"] == pytest.approx(1 / 2)
    merged = eval_people.summary(eval_people.merge([eval_people.score_outputs(frames)] * 2))
    assert merged["false_sure"] == pytest.approx(1 / 2)


def test_handeval_people_without_the_second_drop_is_one_clear_error(tmp_path, capsys):
    from handmocap.training.eval_cli import main
    assert main(["people", "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "video/wild" in err and "Traceback" not in err


def test_jittered_frames_move_each_pixel_by_at_most_one_level_the_same_way_per_seed(monkeypatch):
    """`handeval people --jitter N`: frames moved by a seeded -1/0/+1, repeatable per seed
    and clip, and the table's mean and spread rows over the runs."""
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (24, 32, 3), np.uint8) for _ in range(3)]
    lab = labels([[(hand(16, 12, 10), 0)]] * 3)
    monkeypatch.setattr(real_data, "load_pseudo_labels", lambda v: lab)
    monkeypatch.setattr(real_data, "read_video", lambda v, frames_=None: enumerate(frames))
    plain = [f[0] for f in eval_people.frames_of_clip("clip.mp4")]
    moved = [f[0] for f in eval_people.frames_of_clip("clip.mp4", jitter_seed=0)]
    again = [f[0] for f in eval_people.frames_of_clip("clip.mp4", jitter_seed=0)]
    other = [f[0] for f in eval_people.frames_of_clip("clip.mp4", jitter_seed=1)]
    for p, m, a, o in zip(plain, moved, again, other):
        d = m.astype(int) - p
        assert np.abs(d).max() == 1 and 0.5 < (d != 0).mean() < 0.8       # 2 in 3 move (less at 0 and 255)
        assert np.array_equal(m, a) and not np.array_equal(m, o)
    runs = [{"found": f, "false_per_frame": 0.1, "median_err": 0.1, "mean_err": 0.2, "pck": 0.5, "side": 0.8,
             "shake": 0.02}
            for f in (0.80, 0.84, 0.82)]
    rows = eval_people.jitter_rows(runs)
    assert rows[-2].startswith("| **mean** | 82.000 |") and rows[-1].startswith("| **spread (max - min)** | 4.000 |")


def test_shake_is_zero_for_steady_motion_and_grows_with_jitter_for_ours_and_the_labels():
    """`handeval people`'s shake column: the median joint's second difference over three
    frames / hand size, for our tracks and for MediaPipe's hands linked frame to frame."""
    steady = [hand(100 + 5 * f, 100) for f in range(3)]
    assert eval_people.shake(steady) == pytest.approx(0.0, abs=1e-6)
    shaken = [steady[0], steady[1] + 4.0, steady[2]]            # the middle frame 4 px off: 8 px / 100 px
    assert eval_people.shake(shaken) == pytest.approx(8 * np.sqrt(2) / 100, rel=1e-3)
    # labels: a hand continued over three frames is scored; one with no hand near it before is not
    prev = [np.stack([steady[0]]), np.stack([steady[1] + 4.0])]
    now = np.stack([steady[2], hand(400, 300)])
    assert eval_people.label_shakes(prev, now) == pytest.approx([8 * np.sqrt(2) / 100], rel=1e-3)
    assert eval_people.label_shakes([np.zeros((0, 21, 2)), prev[1]], now) == []
