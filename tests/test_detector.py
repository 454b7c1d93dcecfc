"""The detector's geometry (crop <-> frame, mirroring of left hands, tracking, track ids)
with dot-drawn hands and fake networks; then the real models, and the node in a graph."""
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import ROOT, graph_env
from handmocap.perception.hand_finder import FoundHand
from handmocap.perception.crops import CropTransform, crop_for_joints, hand_angle, head_angle_in_frame, palm_angle
from handmocap.perception.detector import CENTRE, DetectorSettings, HandDetector
from handmocap.perception.tracks import HANDEDNESS_MEMORY, Track
from handmocap.perception.rotations import mirror_points
from handmocap.perception.skeleton import normalize_joints

W, H = 640, 480
DETNET = ROOT / "models" / "detnet.onnx"
FINDER = ROOT / "models" / "finder.onnx"
CLIP = ROOT / "data" / "demo" / "hand_clip.mp4"

# ------------------------------------------------------------------ dot hands
# Hands drawn as 21 coloured dots, and a fake DetNet and hand finder that read them back:
# the fake DetNet finds each joint's colour in the crop it is given, so its 2D answer is
# right only if the crop was cut where the detector says it was. A dot hand "appears
# right" when its thumb tip is left of its little tip (image x).
JOINT_COLOURS = np.array([(200, 240 - 11 * j, 20 + 11 * j) for j in range(21)], np.uint8)   # BGR
RADIUS = 4
DOT_TOL = 2.0    # px: the fake DetNet reads a dot to about one crop pixel (~2 frame px at these sizes)


def canonical_hand(centre, size, right=True):
    """(21,2) px joints of an upright hand (fingers up) of joint-box height ~size."""
    base_x = np.array([-0.45, -0.22, 0.0, 0.18, 0.34])
    length = np.array([0.45, 0.6, 0.65, 0.6, 0.5])
    uv = np.zeros((21, 2))
    for f in range(5):
        for k in range(4):
            t = (k + 1) / 4
            uv[1 + 4 * f + k] = (base_x[f] * (1 + 0.4 * t) - (0.25 * t if f == 0 else 0), -0.35 - length[f] * t)
    uv[1:5, 1] += 0.3                                # thumb lower
    uv *= size
    if not right:
        uv[:, 0] *= -1
    return uv + np.asarray(centre, np.float64)


def draw(frame, uv):
    for j, (u, v) in enumerate(uv):
        cv2.circle(frame, (int(round(u)), int(round(v))), RADIUS, tuple(int(c) for c in JOINT_COLOURS[j]), -1)
    return frame


def find_dots(image_bgr, tol=5):
    """(21,2) centroids of each joint colour (NaN where absent)."""
    img = image_bgr.astype(np.int16)
    uv = np.full((21, 2), np.nan)
    for j, c in enumerate(JOINT_COLOURS.astype(np.int16)):
        ys, xs = np.nonzero(np.all(np.abs(img - c) <= tol, axis=-1))
        if len(xs):
            uv[j] = xs.mean(), ys.mean()
    return uv


def appears_right(uv):
    return float(uv[4, 0] < uv[20, 0])


class FakeDetNet:
    """DetNetRunner's interface: crops (N,128,128,3) RGB -> uv, xyz, confidence, presence,
    handedness. xyz: the 2D joints lifted to z = 0, normalized (or `xyz_right`, a fixed
    right hand, when given)."""

    def __init__(self, xyz_right=None, prefers_upright=False, right_bias=0.0, angle_head=None):
        self.xyz_right = xyz_right
        self.prefers_upright = prefers_upright     # heatmap peaks fall as the hand turns from upright
        self.right_bias = right_bias               # logit added to the handedness head: a biased head
        # with a (length, error radians): a `hand_angle` output, the dots' angle plus error, that long
        self.angle_head = angle_head
        self.calls = 0

    def __call__(self, crops_rgb):
        self.calls += 1
        out = {k: [] for k in ("uv", "xyz", "confidence", "presence", "handedness")}
        for crop in crops_rgb:
            uv = find_dots(np.ascontiguousarray(crop[..., ::-1]))
            seen = np.all(np.isfinite(uv), axis=1)
            ok = seen.sum() >= 18
            uv = np.where(seen[:, None], uv, np.nanmean(uv, axis=0) if seen.any() else 64.0)
            xyz = normalize_joints(np.concatenate([uv, np.zeros((21, 1))], 1)) if self.xyz_right is None \
                else self.xyz_right
            out["uv"].append(uv)
            out["xyz"].append(xyz)
            upright = 1.0
            if self.prefers_upright and ok:
                wrist_to_base = uv[9] - uv[0]
                upright = max(0.2, -wrist_to_base[1] / (np.linalg.norm(wrist_to_base) + 1e-9))
            out["confidence"].append(seen.astype(np.float32) * upright)
            out["presence"].append(1.0 if ok else 0.0)
            sure = 2.0 * (2 * appears_right(uv) - 1) + self.right_bias
            out["handedness"].append(1 / (1 + np.exp(-sure)) if ok else 0.5)
            if self.angle_head is not None:
                length, error = self.angle_head
                a = hand_angle(uv) + error
                out.setdefault("hand_angle", []).append(length * np.array([np.cos(a), np.sin(a)]))
        return {k: np.asarray(v, np.float32) for k, v in out.items()}


class FakeFinder:
    """HandFinder's interface: blobs of dots -> FoundHand (joint box, score 1, right_prob)."""

    def __init__(self, wrong_handedness=False):
        self.calls = 0
        self.wrong_handedness = wrong_handedness

    def find(self, image_bgr, threshold=None, max_hands=2):
        self.calls += 1
        mask = (image_bgr.max(axis=-1) > 30).astype(np.uint8)
        mask = cv2.dilate(mask, np.ones((81, 81), np.uint8))
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask)
        found = []
        for k in np.argsort(-stats[1:, cv2.CC_STAT_AREA])[:max_hands] + 1:
            sub = np.where((labels == k)[..., None], image_bgr, 0)
            uv = find_dots(sub)
            if np.isfinite(uv).all(axis=1).sum() < 18:
                continue
            box = np.concatenate([np.nanmin(uv, 0), np.nanmax(uv, 0)])
            right = appears_right(uv)
            found.append(FoundHand(box, 1.0, 1.0 - right if self.wrong_handedness else right))
        return found


@pytest.mark.parametrize("mirrored,angle", [(False, 0.0), (True, 0.0), (False, 2.5), (True, -0.7)])
def test_crop_round_trip_and_pixels_land_where_the_transform_says(mirrored, angle):
    rng = np.random.default_rng(0)
    for _ in range(20):
        crop = CropTransform.around(rng.uniform(-50, 700, 2), rng.uniform(30, 600), mirrored=mirrored, angle=angle)
        uv = rng.uniform(-100, 700, (21, 2))
        np.testing.assert_allclose(crop.to_frame(crop.to_crop(uv)), uv, atol=1e-9)
    frame = np.zeros((H, W, 3), np.uint8)
    # inside (shrunk by 2 first), past two edges, small, large and past an edge (shrunk by 4),
    # 3.3x and 5.5x the crop (shrunk by 2 and 4, then bilinear by 1.6 and 1.4)
    for centre, side in (((300, 200), 257), ((20, 460), 200), ((600, 30), 90), ((330, 260), 600),
                         ((310, 240), 420), ((290, 250), 700)):
        crop = CropTransform.around(centre, side, mirrored=mirrored, angle=angle)
        dot = np.array(centre) + (17, -11)
        frame[:] = 0
        cv2.circle(frame, tuple(int(v) for v in dot), 6, (255, 255, 255), -1)
        img = crop.cut(frame).astype(np.float64)[..., 0]
        ys, xs = np.mgrid[:128, :128]
        seen = np.array([(img * xs).sum(), (img * ys).sum()]) / img.sum()
        np.testing.assert_allclose(seen, crop.to_crop(dot), atol=0.3)


def test_the_crop_of_a_hand_at_angle_zero_is_the_axis_aligned_one_exactly():
    for centre, side in (((300, 200), 257), ((20, 460), 200), ((600, 30), 90)):
        crop = CropTransform.around(centre, side)
        assert crop.angle == 0.0
        np.testing.assert_array_equal(crop.box, [crop.x0 - 0.5, crop.y0 - 0.5, crop.x0 + crop.side - 0.5,
                                                 crop.y0 + crop.side - 0.5])
        uv = np.array([[crop.x0, crop.y0], [crop.x0 + crop.side - 1, crop.y0 + 3]], float)
        np.testing.assert_allclose(crop.to_crop(uv), (uv - [crop.x0, crop.y0] + 0.5) * 128 / crop.side - 0.5,
                                   atol=1e-9)


def turned_hand(centre, size, angle, right=True):
    """canonical_hand turned by `angle` radians clockwise (in the image) about its centre."""
    uv = canonical_hand(centre, size, right) - np.asarray(centre, float)
    c, s = np.cos(angle), np.sin(angle)
    return uv @ np.array([[c, s], [-s, c]]) + np.asarray(centre, float)   # x' = c x - s y, y' = s x + c y


@pytest.mark.parametrize("angle", [np.pi, np.pi / 2, -2.2])
def test_an_upright_crop_shows_a_turned_hand_upright_and_its_joints_come_back_in_frame_axes(angle):
    uv_true = turned_hand((320, 240), 150, angle)
    assert abs(np.angle(np.exp(1j * (hand_angle(uv_true) - angle)))) < 1e-9
    crop = crop_for_joints(uv_true, upright_step=0)
    in_crop = crop.to_crop(uv_true)
    assert in_crop[0, 1] > in_crop[9, 1] and abs(in_crop[0, 0] - in_crop[9, 0]) < 1e-6   # wrist straight below
    frame = draw(np.zeros((H, W, 3), np.uint8), uv_true)
    turned, plain = detector(upright_step=0), detector(upright_step=None)
    for _ in range(3):
        out_t, out_p = turned.process(frame), plain.process(frame)
    assert abs(turned.tracks[0].crop.angle - angle) < 0.05 or abs(abs(turned.tracks[0].crop.angle - angle)
                                                                 - 2 * np.pi) < 0.05
    assert plain.tracks[0].crop.angle == 0.0
    for out in (out_t, out_p):
        np.testing.assert_allclose(out[0]["uv"], np.round(uv_true), atol=DOT_TOL)
        # the fake DetNet lifts the crop's 2D to 3D: back in frame axes it is the frame's 2D lifted
        lifted = normalize_joints(np.concatenate([out[0]["uv"], np.zeros((21, 1))], 1))
        np.testing.assert_allclose(out[0]["xyz_rel"], lifted, atol=0.03)


def foreshortened_hand(centre, size):
    """canonical_hand with its wrist drawn up beside the middle finger's base, as a palm seen with
    the fingers toward the camera shows it: the wrist -> middle knuckle points left and down."""
    uv = canonical_hand(centre, size)
    uv[0] = uv[9] + np.array([0.12, 0.06]) * size
    return uv


@pytest.mark.parametrize("angle", [0.0, 0.8, np.pi, -2.2])
def test_the_palms_angle_turns_with_the_hand_and_holds_where_the_wrist_is_foreshortened(angle):
    c = np.array([320.0, 240.0])
    turn = lambda uv: (uv - c) @ np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]]) + c   # noqa: E731
    apart = lambda a, b: abs(np.angle(np.exp(1j * (a - b))))                                                      # noqa: E731
    assert apart(palm_angle(turn(canonical_hand(c, 150))), angle) < np.radians(3)   # an open hand: as hand_angle
    short = turn(foreshortened_hand(c, 150))
    assert apart(hand_angle(short), angle) > np.radians(60)                      # the wrist's way: a quarter turn off
    assert apart(palm_angle(short), angle) < np.radians(15)
    both = np.stack([short, turn(canonical_hand(c, 150))])
    np.testing.assert_allclose(palm_angle(both), [palm_angle(short), palm_angle(both[1])])   # (..., 21, 2)


def test_a_tracked_crop_turns_by_the_palm_when_asked():
    """turn_by="palm": a tracked crop is turned by crops.palm_angle of the last joints, so a palm
    whose wrist shows beside the middle knuckle keeps an upright crop; by default the wrist ->
    middle knuckle turns it a quarter turn."""
    frame = draw(np.zeros((H, W, 3), np.uint8), foreshortened_hand((320, 240), 150))
    angles = {}
    for turn_by in ("wrist_knuckle", "palm"):
        det = HandDetector(FakeDetNet(), FakeFinder(), turn_by=turn_by, smooth_min_cutoff=None)
        for _ in range(3):
            out = det.process(frame)
        assert len(out) == 1
        angles[turn_by] = det.tracks[0].crop.angle
    assert abs(angles["palm"]) < 1e-9 and abs(abs(angles["wrist_knuckle"]) - np.pi / 2) < 1e-9, angles
    with pytest.raises(ValueError, match="turn_by"):
        HandDetector(FakeDetNet(), FakeFinder(), turn_by="thumb")


def test_a_new_track_takes_the_quarter_turn_detnet_believes_most():
    """An upside-down hand, found by a finder that knows nothing of which way it points: with
    upright crops the new track tries the three other quarter turns and keeps the one whose
    heatmap peaks are highest (the fake DetNet's peaks fall as a hand turns from upright)."""
    uv_true = turned_hand((320, 240), 150, np.pi - 0.3)
    frame = draw(np.zeros((H, W, 3), np.uint8), uv_true)
    for step, angle in ((90, np.pi), (0, np.pi - 0.3), (None, 0.0)):
        det = HandDetector(FakeDetNet(prefers_upright=True), FakeFinder(), upright_step=step, birth_confidence=0.5)
        out = det.process(frame)
        assert len(out) == (0 if step is None else 1)        # upside down, its peaks stay below birth
        if step is not None:
            assert abs(abs(det.tracks[0].crop.angle) - abs(angle)) < 0.05, det.tracks[0].crop.angle
            # first look, three more turns, the refinement; the first look and the refinement
            # also flipped for the mirror vote; and one re-read (settle_side): the upside-down
            # first look read the hand as left, so the refinement was cut mirrored, and the
            # readings on it turned the side back to right
            assert det.stats["crops"] == 1 + 3 + 1 + 2 + 1 and det.stats["side_rereads"] == 1
            np.testing.assert_allclose(out[0]["uv"], np.round(uv_true), atol=DOT_TOL)


def test_a_doubted_tracked_hand_tries_the_other_quarter_turns_when_asked():
    """turn_check_below (off by default): a tracked hand whose mean heatmap peak on this frame
    is below it is also read at the three other quarter turns of its crop, at most once every
    turn_check_every frames of its track, and the turn DetNet is surest of is published."""
    from dataclasses import replace
    frame = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((320, 240), 150))
    assert HandDetector(FakeDetNet(), FakeFinder()).turn_check_below is None
    peaks, checks = {}, {}
    for below in (None, 1.0):
        det = HandDetector(FakeDetNet(prefers_upright=True), FakeFinder(), turn_check_below=below, turn_check_every=3,
                           smooth_min_cutoff=None)
        det.process(frame)                                    # born upright
        peaks[below] = []
        for _ in range(4):                                    # each frame's crop cut upside down
            det.tracks[0].crop = replace(det.tracks[0].crop, angle=det.tracks[0].crop.angle + np.pi)
            peaks[below].append(float(det.process(frame)[0]["confidence"].mean()))
        checks[below] = det.stats["turn_checks"]
    assert checks == {None: 0, 1.0: 2}                        # frames 1 and 4 of the track: every 3
    assert peaks[1.0][0] > peaks[None][0] + 0.2 and peaks[1.0][3] > peaks[None][3] + 0.2   # read upright there
    np.testing.assert_allclose(peaks[1.0][1:3], peaks[None][1:3])


@pytest.mark.parametrize("mirrored", [False, True])
@pytest.mark.parametrize("crop_angle", [0.0, 0.5, -1.2, 2.5])
def test_the_angle_heads_reading_on_any_crop_is_the_hands_angle_in_the_frame(crop_angle, mirrored):
    uv = turned_hand((320, 240), 150, 0.7)
    crop = CropTransform.around(np.array([300.0, 250.0]), 220.0, 128, mirrored=mirrored, angle=crop_angle)
    a = hand_angle(crop.to_crop(uv))                       # the angle the head reads in the crop's pixels
    assert abs(head_angle_in_frame(crop, (np.cos(a), np.sin(a))) - 0.7) < 1e-9
    assert abs(crop_for_joints(uv, upright_step=90, angle=1.4).angle - np.pi / 2) < 1e-9   # rounded as the joints'
    assert abs(crop_for_joints(uv, upright_step=90).angle) < 1e-9


def test_a_crop_turns_by_the_angle_head_where_it_is_sure_and_a_new_hand_is_read_at_its_turn():
    """turn_from_head (off by default): with a DetNet that has an angle head, a tracked crop turns
    by the head's angle where the head's (cos, sin) is that long, by the joints' elsewhere; a
    new hand the head is sure of is read at the head's quarter turn, not at all four."""
    uv_true = turned_hand((320, 240), 150, np.pi - 0.3)      # upside down
    frame = draw(np.zeros((H, W, 3), np.uint8), uv_true)
    assert HandDetector(FakeDetNet(), FakeFinder()).turn_from_head is None
    birth_crops = {}
    # (head's length, its error, DetNet's peaks fall off upright): sure and right, unsure, sure and wrong
    for length, error, upright in ((0.9, 0.0, True), (0.3, 0.0, True), (0.9, np.pi / 2, False)):
        det = HandDetector(FakeDetNet(prefers_upright=upright, angle_head=(length, error)), FakeFinder(),
                           birth_confidence=0.5, turn_from_head=0.5, smooth_min_cutoff=None)
        det.process(frame)
        birth_crops[length, error] = det.stats["crops"]
        sure = length >= 0.5
        assert det.stats["head_turns"] == int(sure)
        for _ in range(3):      # the head's turn every frame: off upright by its error (either way: mirrored)
            off = abs(np.angle(np.exp(1j * (det.tracks[0].crop.angle - np.pi))))
            assert abs(off - (error if sure else 0.0)) < 0.05, (length, error, off)
            det.process(frame)
    assert birth_crops[0.9, 0.0] == birth_crops[0.3, 0.0] - 2     # one turned read instead of three
    # the head for new hands only: read at its (wrong) turn when born, then turned by the joints, upright
    det = HandDetector(FakeDetNet(angle_head=(0.9, np.pi / 2)), FakeFinder(), birth_confidence=0.5,
                       turn_from_head=0.5, turn_tracked_from_head=False, smooth_min_cutoff=None)
    for _ in range(2):
        det.process(frame)
        assert det.stats["head_turns"] == 1 and abs(np.angle(np.exp(1j * (det.tracks[0].crop.angle - np.pi)))) < 0.05
    # a head 50 degrees off after birth: within turn_head_margin (60) the crop keeps its turn, at 45 it turns
    down = draw(np.zeros((H, W, 3), np.uint8), turned_hand((320, 240), 150, np.pi))
    for margin, turns in ((60.0, False), (45.0, True)):
        det = HandDetector(FakeDetNet(angle_head=(0.9, 0.0)), FakeFinder(), birth_confidence=0.5,
                           turn_from_head=0.5, turn_head_margin=margin, smooth_min_cutoff=None)
        det.process(down)
        det.detnet.angle_head = (0.9, np.radians(50))
        det.process(down)
        off = abs(np.angle(np.exp(1j * (det.tracks[0].crop.angle - np.pi))))
        assert abs(off - (np.pi / 2 if turns else 0.0)) < 0.05, (margin, off)
    # a head that swings 50 degrees either way from frame to frame: each swing turns the crop at a
    # margin of 45; its running mean (turn_head_memory) stays near the hand's angle, and the crop too
    for memory, turns in ((None, True), (0.3, False)):
        det = HandDetector(FakeDetNet(angle_head=(0.9, 0.0)), FakeFinder(), birth_confidence=0.5,
                           turn_from_head=0.5, turn_head_margin=45.0, turn_head_memory=memory,
                           smooth_min_cutoff=None)
        det.process(down)
        angles = []
        for k in range(6):
            det.detnet.angle_head = (0.9, np.radians(50) * (-1) ** k)
            det.process(down)
            angles.append(det.tracks[0].crop.angle)
        assert (len(set(np.round(angles, 3))) > 1) == turns, (memory, angles)
    with pytest.raises(ValueError, match="turn_from_head"):
        HandDetector(FakeDetNet(), FakeFinder(), turn_from_head=-1.0)
    with pytest.raises(ValueError, match="turn_head_memory"):
        HandDetector(FakeDetNet(), FakeFinder(), turn_head_memory=0.0)
    with pytest.raises(ValueError, match="turn_head_margin"):
        HandDetector(FakeDetNet(), FakeFinder(), turn_head_margin=30.0)


def test_crop_for_joints_is_the_square_around_the_joint_box_times_the_scale():
    uv = canonical_hand((320, 240), 150)
    crop = crop_for_joints(uv, scale=1.5)
    side = np.max(uv.max(0) - uv.min(0))
    assert abs(crop.side - 1.5 * side) <= 1
    np.testing.assert_allclose((crop.box[:2] + crop.box[2:]) / 2, (uv.min(0) + uv.max(0)) / 2, atol=1)


def detector(**kw):
    """A HandDetector on the fakes; its published joints unfiltered unless asked (these tests
    check the tracking itself to within DOT_TOL; the filter's own tests set it)."""
    kw.setdefault("smooth_min_cutoff", None)
    return HandDetector(FakeDetNet(), FakeFinder(), **kw)


def test_a_mirrored_hand_gives_back_the_mirrored_keypoints():
    right = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160))
    left = np.ascontiguousarray(right[:, ::-1])
    out_r, out_l = detector().process(right), detector().process(left)
    assert [h["handedness"] for h in out_r] == ["right"] and [h["handedness"] for h in out_l] == ["left"]
    uv_r, uv_l = out_r[0]["uv"], out_l[0]["uv"]
    np.testing.assert_allclose(uv_l[:, 0], W - 1 - uv_r[:, 0], atol=0.5)
    np.testing.assert_allclose(uv_l[:, 1], uv_r[:, 1], atol=0.5)
    np.testing.assert_allclose(uv_r, np.round(canonical_hand((250, 300), 160)), atol=DOT_TOL)   # dots are drawn at whole px
    # xyz_rel is the hand as seen: the left one is the mirror image of the right one
    np.testing.assert_allclose(out_l[0]["xyz_rel"], mirror_points(out_r[0]["xyz_rel"]), atol=0.02)


def test_detnets_handedness_overrides_a_wrong_finder_at_once():
    frame = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160, right=False))
    det = HandDetector(FakeDetNet(), FakeFinder(wrong_handedness=True))
    hands = det.process(frame)
    assert [h["handedness"] for h in hands] == ["left"]
    np.testing.assert_allclose(hands[0]["uv"], np.round(canonical_hand((250, 300), 160, right=False)), atol=DOT_TOL)


def test_a_new_hand_whose_side_turns_on_its_first_frame_is_read_again_as_that_side():
    """The finder calls a left hand right, so its first crop is cut unmirrored; DetNet's
    readings then turn the track left, here (the finder's side weighing 0.8 readings) only on
    the third, after the crop was re-cut. Read as it was cut, the published left hand would
    carry a right hand's 3D (a photo has no next frame to mend it); settled, the crop is
    mirrored and read again: the 3D is the mirror image of the right hand DetNet sees."""
    xyz_right = normalize_joints(np.concatenate([canonical_hand((0, 0), 1.0), np.zeros((21, 1))], 1))
    frame = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160, right=False))
    got = {}
    for settle in (False, True):
        det = HandDetector(FakeDetNet(xyz_right=xyz_right), FakeFinder(wrong_handedness=True),
                           upright_step=None, settle_side=settle, finder_handedness=0.8)
        (hand,) = det.process(frame)
        assert hand["handedness"] == "left"
        got[settle] = (hand["xyz_rel"], det.stats["side_rereads"], det.stats["crops"])
    np.testing.assert_allclose(got[True][0], mirror_points(xyz_right), atol=1e-5)
    assert np.abs(got[False][0] - mirror_points(xyz_right)).max() > 0.1
    assert got[True][1:] == (1, 5) and got[False][1:] == (0, 4)      # one crop more: the re-read


def test_grey_frames_go_to_the_grey_finder_and_colour_frames_to_the_other():
    """A mono camera's frames (three equal channels, give or take a few levels of video
    chroma) are searched by `grey_finder`; colour frames by `finder`, as before."""
    from handmocap.perception.hand_finder import is_grey
    rng = np.random.default_rng(0)
    colour = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160))
    grey = np.repeat(cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)[..., None], 3, -1)
    noisy = np.clip(grey.astype(int) + rng.integers(-3, 4, grey.shape), 0, 255).astype(np.uint8)
    assert is_grey(grey) and is_grey(noisy) and not is_grey(colour)
    finder, grey_finder = FakeFinder(), FakeFinder()
    det = HandDetector(FakeDetNet(), finder, grey_finder=grey_finder)
    det.process(colour)
    assert (finder.calls, grey_finder.calls) == (1, 0)
    det.reset()
    det.process(noisy)
    assert (finder.calls, grey_finder.calls) == (1, 1) and det.stats["grey_finder_runs"] == 1
    assert HandDetector(FakeDetNet(), finder).grey_finder is None      # none given: one finder for all
    # the DetNet for grey frames reads every crop of a grey frame, the other every colour one
    net, grey_net = FakeDetNet(), FakeDetNet()
    det = HandDetector(net, FakeFinder(), grey_detnet=grey_net)
    det.process(colour)
    assert net.calls > 0 and grey_net.calls == 0
    det.reset()
    det.process(noisy)                      # the fake finder sees no coloured dots: no track here
    assert det.grey_frames and grey_net.calls == 0
    det._run(noisy, [CropTransform.around(np.array([250.0, 250.0]), 200.0)])
    assert grey_net.calls == 1


def test_the_mirror_vote_cancels_a_handedness_head_biased_to_one_side():
    """A head that leans 3 logits towards "right" calls a left hand right on its crop
    (-2 + 3 > 0); on the crop flipped, which shows a right hand, it says right all the more
    (2 + 3), i.e. the hand as filmed is left: the two readings' mean is the head's unbiased
    answer (-2). Every `mirror_vote_every` frames of a track, and on its first crops."""
    frame = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160, right=False))
    for every, side in ((0, "right"), (3, "left")):
        net = FakeDetNet(right_bias=3.0)
        # the finder's wrong side cuts the first crop unmirrored, as filmed
        det = HandDetector(net, FakeFinder(wrong_handedness=True), finder_handedness=0.0, mirror_vote_every=every,
                           upright_step=None)
        assert [h["handedness"] for h in det.process(frame)] == [side], every
    crops = [det.stats["crops"]]
    for _ in range(6):                       # a tracked hand: one crop a frame, two every third
        det.process(frame)
        crops.append(det.stats["crops"])
    assert np.diff(crops).tolist() == [1, 1, 2, 1, 1, 2]
    assert det.tracks[0].right_logit < 0


def test_handedness_memory_sets_how_long_contrary_readings_take_to_turn_a_track():
    """After 40 sure "right" readings, sure "left" ones turn the running mean in about
    0.7 x memory readings (its first `memory` readings count alike, older ones then fade)."""
    def readings_to_turn(memory):
        t = Track(0, CropTransform.around(np.array([300.0, 300.0]), 200.0), memory=memory)
        for _ in range(40):
            t.add_head_reading(0.95, mirrored=False)
        for n in range(1, 200):
            t.add_head_reading(0.05, mirrored=False)
            if not t.is_right:
                return n
    assert [readings_to_turn(m) for m in (10, 20, 60)] == [7, 14, 38]
    det = HandDetector(FakeDetNet(), FakeFinder(), handedness_memory=10)
    det.process(draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160)))
    assert det.handedness_memory == 10 and det.tracks[0].memory == 10
    assert HandDetector(FakeDetNet(), FakeFinder()).handedness_memory == Track(0, None).memory == HANDEDNESS_MEMORY


def test_a_given_handedness_holds_against_the_head_and_the_finder_and_skips_the_vote():
    """handedness="left": a head sure of "right" and a finder that says right change nothing;
    every crop is mirrored (DetNet sees a right hand), and no flipped crop is read."""
    frame = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160, right=False))
    det = HandDetector(FakeDetNet(right_bias=6.0), FakeFinder(wrong_handedness=True), handedness="left",
                       upright_step=None)
    crops = []
    for _ in range(7):
        hands = det.process(frame)
        assert [h["handedness"] for h in hands] == ["left"]
        crops.append(det.stats["crops"])
    np.testing.assert_allclose(hands[0]["uv"], np.round(canonical_hand((250, 300), 160, right=False)), atol=DOT_TOL)
    assert det.tracks[0].crop.mirrored and det.tracks[0].fixed_side
    assert np.diff(crops).tolist() == [1] * 6                  # one crop a frame: no mirror vote
    with pytest.raises(ValueError, match="handedness"):
        HandDetector(FakeDetNet(), FakeFinder(), handedness="both")


def two_hand_frames(n, drop=()):
    """A right hand moving right on the left, a left hand moving left on the right; the left
    one is missing in frames `drop`. Returns frames and true uv per hand."""
    frames, truth = [], []
    for i in range(n):
        frame = np.zeros((H, W, 3), np.uint8)
        r = canonical_hand((150 + 1.5 * i, 330 - i), 130, right=True)
        l_ = canonical_hand((500 - 1.5 * i, 320 + i), 120, right=False)
        draw(frame, r)
        if i not in drop:
            draw(frame, l_)
        frames.append(frame)
        truth.append((np.round(r), None if i in drop else np.round(l_)))   # dots are drawn at whole px
    return frames, truth


def test_track_ids_are_stable_over_a_two_hand_sequence_and_never_reused():
    det = detector(redetect_every=5, reseed_iou=0.0)
    frames, truth = two_hand_frames(40, drop=range(20, 25))
    ids = []
    for i, (frame, (r, l_)) in enumerate(zip(frames, truth)):
        hands = {h["handedness"]: h for h in det.process(frame)}
        # a returning hand is found by the next finder run, at most redetect_every frames later
        want = {"right"} if l_ is None else {"right", "left"}
        assert set(hands) == want or (25 <= i < 30 and set(hands) == {"right"}), i
        np.testing.assert_allclose(hands["right"]["uv"], r, atol=DOT_TOL)
        if "left" in hands:
            np.testing.assert_allclose(hands["left"]["uv"], l_, atol=DOT_TOL)
        ids.append({k: h["track_id"] for k, h in hands.items()})
    assert all(d["right"] == ids[0]["right"] for d in ids)
    assert all(d["left"] == ids[0]["left"] for d in ids[:20])
    assert all(d["left"] == ids[30]["left"] for d in ids[30:])
    assert ids[30]["left"] not in (ids[0]["left"], ids[0]["right"])   # a lost hand comes back as a new track
    # the finder ran at the start, after the loss, then every 5 frames until the hand was back
    assert det.stats["finder_runs"] <= 1 + 1 + 2


@pytest.mark.parametrize("name", sorted(__import__("handmocap.nodes.detector", fromlist=["NULLABLE"]).NULLABLE))
def test_every_setting_the_detector_node_lets_be_null_runs_as_null(name):
    """The node passes null through as None for its NULLABLE params only: each of them must
    run as None (off) on a two-hand sequence and still follow both hands."""
    det = detector(**{name: None})
    frames, truth = two_hand_frames(6)
    for frame, (r, _) in zip(frames, truth):
        hands = {h["handedness"]: h for h in det.process(frame)}
    assert set(hands) == {"right", "left"}
    np.testing.assert_allclose(hands["right"]["uv"], r, atol=DOT_TOL)


def test_the_track_follows_the_heatmap_peaks_and_publishes_the_finer_read_out():
    """DetNet's `uv_peak` (the heatmap peaks) cuts the next crop and judges the track; `uv`
    (the soft-argmax read-out) is what the hand publishes. A read-out that gathers every
    joint at the crop's centre must neither steer nor shrink the track."""
    class CentredDetNet(FakeDetNet):
        def __call__(self, crops_rgb):
            out = super().__call__(crops_rgb)
            out["uv_peak"] = out["uv"].copy()
            out["uv"] = np.full_like(out["uv"], 63.5)
            return out

    det = HandDetector(CentredDetNet(), FakeFinder(), redetect_every=1000)
    for i in range(20):
        truth = canonical_hand((200 + 8 * i, 260 - 3 * i), 150)
        hands = det.process(draw(np.zeros((H, W, 3), np.uint8), truth))
        assert len(hands) == 1, i
        centre = (hands[0]["bbox"][:2] + hands[0]["bbox"][2:]) / 2
        # published: one point, the crop's centre; the crop stays on the moving hand, its size too
        assert np.ptp(hands[0]["uv"], axis=0).max() < 1e-3
        np.testing.assert_allclose(hands[0]["uv"][0], centre, atol=1.0)
        assert np.linalg.norm(centre - (truth.min(0) + truth.max(0)) / 2) < 10, i
        assert np.ptp(hands[0]["bbox"].reshape(2, 2), axis=0).max() > 150, i
    assert det.finder.calls == 1


def test_tracked_hands_do_not_run_the_finder_unless_it_checks_the_tracks():
    det = detector(redetect_every=5, reseed_iou=0.0)
    frames, _ = two_hand_frames(30)
    for f in frames:
        det.process(f)
    # + three more quarter turns and the refinement of each new track
    # and the mirror vote: each new track's first and refined crop, then every sixth frame (ages 6 .. 24)
    assert det.finder.calls == 1 and det.stats["crops"] == 2 * 30 + 2 * 3 + 2 + 2 * 2 + 2 * 4
    # both slots held: the finder checks the tracks every redetect_every_full frames (None: every
    # redetect_every), and the checks read no crop when every box matches its track
    for full, calls in ((None, 1 + 29 // 5), (15, 1 + 29 // 15)):
        det = detector(redetect_every=5, redetect_every_full=full)
        for f in frames:
            det.process(f)
        assert det.finder.calls == calls and det.stats["reseeds"] == 0
        assert det.stats["crops"] == 2 * 30 + 2 * 3 + 2 + 2 * 2 + 2 * 4
    # one slot free (max_hands 3): every redetect_every frames, whatever redetect_every_full says
    det = detector(redetect_every=5, redetect_every_full=15, max_hands=3)
    for f in frames:
        det.process(f)
    assert det.finder.calls == 1 + 29 // 5


def test_a_periodic_finder_run_waits_for_a_frame_without_a_mirror_vote():
    frames, _ = two_hand_frames(60)

    def events(finder_waits):
        """Per frame after the first: (the finder ran, a track was due a mirror vote: its age a
        multiple of mirror_vote_every, 6, as the frame came)."""
        det = detector(redetect_every=10, redetect_every_full=10, finder_waits=finder_waits)
        out = []
        for f in frames:
            calls, voting = det.finder.calls, any(t.age % 6 == 0 for t in det.tracks)
            det.process(f)
            out.append((det.finder.calls > calls, voting))
        return out[1:]

    at_once = lambda ev: sum(found and voted for found, voted in ev)   # noqa: E731
    runs = lambda ev: [i for i, (found, _) in enumerate(ev) if found]   # noqa: E731
    assert at_once(events(0)) > 0                # finder every 10 frames, votes every 6: they meet
    waited = events(3)
    assert at_once(waited) == 0 and len(runs(waited)) >= len(runs(events(0))) - 1
    assert max(np.diff(runs(waited))) <= 10 + 3


def test_a_track_whose_joints_left_the_found_hand_is_reseeded_from_the_finder():
    det = detector(redetect_every=5, redetect_every_full=5)
    frames, truth = two_hand_frames(12)
    for f in frames[:3]:
        det.process(f)
    # a track that slid up the "forearm": its joints 120 px above the hand, its crop large
    # enough to still hold the hand
    t = next(t for t in det.tracks if t.is_right)
    t.uv = truth[2][0] - (0, 120)
    t.crop = CropTransform.around(t.uv.mean(0), 400)
    det.frames_since_find = det.redetect_every - 1              # the finder's check comes next frame
    for f in frames[3:]:
        hands = {h["handedness"]: h for h in det.process(f)}
    assert det.stats["reseeds"] == 1
    assert {h["track_id"] for h in hands.values()} == {0, 1}               # the same tracks
    np.testing.assert_allclose(hands["right"]["uv"], truth[-1][0], atol=DOT_TOL)


def test_a_reseed_onto_a_box_detnet_does_not_believe_is_refused():
    """A track's crop holds a finder box of something else (no hand there) that its joints
    do not overlap: with reseed_margin the track stays on its hand, since DetNet's peaks on
    that box's crop are far below the track's; without it the track is moved onto the box."""
    uv_true = canonical_hand((250, 300), 160)
    frame = draw(np.zeros((H, W, 3), np.uint8), uv_true)

    class FalseBoxFinder:              # a box in a corner of the track's crop, off the hand
        def __init__(self, crop):
            x0, y0 = crop.box[:2]
            self.box = np.array([x0 + 4.0, y0 + 4.0, x0 + 44.0, y0 + 44.0])

        def find(self, image_bgr, threshold=None, max_hands=2):
            return [FoundHand(self.box, 1.0, 1.0)]
    for margin, reseeds in ((0.2, 0), (None, 1)):
        det = detector(redetect_every=5, reseed_margin=margin)
        for _ in range(3):
            det.process(frame)
        det.finder, det.frames_since_find = FalseBoxFinder(det.tracks[0].crop), det.redetect_every - 1
        det.process(frame)
        assert det.stats["reseeds"] == reseeds
        hands = det.process(frame)
        if reseeds:
            assert hands == [] or np.abs(hands[0]["uv"] - uv_true).max() > 50
        else:
            np.testing.assert_allclose(hands[0]["uv"], np.round(uv_true), atol=DOT_TOL)


class DimDetNet(FakeDetNet):
    """FakeDetNet whose heatmap peaks (confidence) are `levels[k]` on its k-th call."""

    def __init__(self, levels):
        super().__init__()
        self.levels = levels

    def __call__(self, crops_rgb):
        out = super().__call__(crops_rgb)
        out["confidence"] *= self.levels[min(self.calls - 1, len(self.levels) - 1)]
        return out


def test_a_found_hand_needs_birth_confidence_and_a_track_lives_down_to_min_confidence():
    frames, _ = two_hand_frames(6)
    # calls: the first frame's crops, its three other quarter turns (dim_at_birth), its refined
    # crops, then one call per frame
    dim_at_birth = HandDetector(DimDetNet([0.2, 0.2, 0.2]), FakeFinder(), birth_confidence=0.3, min_confidence=0.15)
    assert [len(dim_at_birth.process(f)) for f in frames[:3]] == [0, 0, 0]
    assert dim_at_birth.stats["unborn"] == 6 and dim_at_birth.stats["finder_runs"] == 3   # tries again each frame
    dims_later = HandDetector(DimDetNet([0.5, 0.5, 0.2, 0.2, 0.1]), FakeFinder(), birth_confidence=0.3,
                              min_confidence=0.15, upright_step=None)   # no quarter-turn call at birth
    assert [len(dims_later.process(f)) for f in frames[:4]] == [2, 2, 2, 0]    # kept at 0.2, lost at 0.1
    assert dims_later.stats["unborn"] == 0


def test_a_second_track_inside_a_hand_is_a_duplicate_and_crops_change_size_slowly():
    det = detector()
    big = canonical_hand((300, 300), 150)
    small = (big - big.mean(0)) * 0.2 + big.mean(0)           # a collapsed prediction on the same hand
    hands = [{"track_id": 0, "score": 0.9, "uv": small}, {"track_id": 1, "score": 0.95, "uv": big},
             {"track_id": 2, "score": 0.8, "uv": big + 400}]
    assert [h["track_id"] for h in det._drop_duplicates(hands)] == [1, 2]
    track = Track(0, crop_for_joints(big))
    assert det._next_crop(track, small).side == pytest.approx(track.crop.side / 1.33, abs=1)


def test_empty_frame_gives_no_hands():
    assert detector().process(np.zeros((H, W, 3), np.uint8)) == []


# ------------------------------------------------------------------ trained models
needs_models = pytest.mark.skipif(not (DETNET.is_file() and FINDER.is_file()),
                                  reason="models/detnet.onnx or models/finder.onnx not committed yet")


@needs_models
def test_real_models_follow_the_rendered_clip():
    truth = np.load(ROOT / "data" / "demo" / "hand_clip.npz")
    det = HandDetector.load()
    cap = cv2.VideoCapture(str(CLIP))
    errors, found = [], 0
    for i in range(len(truth["uv"])):
        ok, frame = cap.read()
        hands = det.process(frame)
        if hands:
            found += 1
            errors.append(np.linalg.norm(hands[0]["uv"] - truth["uv"][i], axis=-1).mean())
    assert found >= 0.9 * len(truth["uv"]), found
    assert np.median(errors) < 16.0, np.median(errors)   # 16,000-iteration DetNet: about 12 px


@needs_models
def test_real_models_find_the_rendered_hand_in_grey_with_the_grey_finder():
    """The rendered clip in grey, read as stills: the bundled grey finder is loaded, searches
    every frame, and the hand is found where it is drawn."""
    truth = np.load(ROOT / "data" / "demo" / "hand_clip.npz")
    det = HandDetector.load()
    assert det.grey_finder is not None
    cap = cv2.VideoCapture(str(CLIP))
    found, stills = 0, 0
    for i in range(0, len(truth["uv"]), 6):
        cap.set(cv2.CAP_PROP_POS_FRAMES, i)
        ok, frame = cap.read()
        grey = np.repeat(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)[..., None], 3, -1)
        det.reset()
        hands = det.process(grey)
        stills += 1
        found += bool(hands) and np.linalg.norm(hands[0]["uv"] - truth["uv"][i], axis=-1).mean() < 30
    assert det.stats["grey_finder_runs"] >= stills
    assert found >= 0.8 * stills, (found, stills)


@needs_models
def test_detector_node_publishes_one_keypoints_message_per_frame(tmp_path, run_dir):
    """replay -> detector -> recorder on the rendered clip: one /hand/keypoints per frame,
    each with the stamp of its image (every_frame: keep-all, so a slow machine loses none)."""
    from handmocap.runtime import codec
    from handmocap.runtime.bag import iter_messages
    bag = tmp_path / "out.mcap"
    lf = tmp_path / "g.yaml"
    lf.write_text(f"""
nodes:
  replay: {{node: replay, params: {{source: {CLIP}, rate: 1.0, fps: 10}}, required: true}}
  detector: {{node: detector, params: {{every_frame: true}}, required: true}}
  recorder: {{node: recorder, params: {{output: {bag}, overwrite: true}}, required: true}}
""")
    r = subprocess.run([sys.executable, "-m", "handmocap.runtime.launch", str(lf)], env=graph_env(run_dir),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    stamps = {"Image": [], "HandKeypoints": []}
    for topic, type_name, payload, _ in iter_messages(bag):
        if type_name in stamps:
            msg = codec.decode(payload, type_name)
            stamps[type_name].append(msg["header"]["stamp_ns"])
    frames = len(np.load(ROOT / "data" / "demo" / "hand_clip.npz")["uv"])
    assert len(stamps["Image"]) == frames
    assert stamps["HandKeypoints"] == stamps["Image"]


def test_a_reseeded_track_does_not_take_a_new_hands_place():
    det = detector(redetect_every=5, max_hands=2)
    frames, truth = two_hand_frames(12, drop=range(0, 3))      # the left hand appears at frame 3
    for f in frames[:3]:
        det.process(f)
    assert len(det.tracks) == 1
    t = det.tracks[0]
    t.uv = truth[2][0] - (0, 120)                              # the right track slid off its hand
    t.crop = CropTransform.around(t.uv.mean(0), 400)
    det.frames_since_find = det.redetect_every - 1
    hands = {h["handedness"]: h for h in det.process(frames[3])}
    assert det.stats["reseeds"] == 1 and set(hands) == {"right", "left"}   # re-seeded, and the new hand found


class ScriptedFinder:
    """HandFinder's interface: the given FoundHands, whatever the image."""

    def __init__(self, found):
        self.found, self.calls = found, 0

    def find(self, image_bgr, threshold=None, max_hands=2):
        self.calls += 1
        return self.found[:max_hands]


def test_two_sure_hands_that_both_read_right_become_a_left_and_a_right():
    """DetNet's handedness head unsure (0.55 for every crop) and the finder only weakly
    wrong about the left hand (0.6 right): both tracks read right. The one with the weaker
    evidence (the left hand) turns from the next frame on, unless opposite_hands is off or
    above DetNet's belief in the hands (their heatmap peaks are 1.0 here)."""
    frames, truth = two_hand_frames(4)

    class UnsureDetNet(FakeDetNet):
        def __call__(self, crops_rgb):
            out = super().__call__(crops_rgb)
            out["handedness"][:] = 0.55
            return out

    class WeakFinder(FakeFinder):
        def find(self, image_bgr, threshold=None, max_hands=2):
            return [FoundHand(f.box, f.score, 1.0 if f.right_prob > 0.5 else 0.6)
                    for f in super().find(image_bgr, threshold, max_hands)]

    def sides(**kwargs):
        det = HandDetector(UnsureDetNet(), WeakFinder(), **kwargs)
        out = [{h["handedness"]: h for h in det.process(f)} for f in frames]
        return det, out

    det, out = sides()
    assert set(out[0]) == {"right"} and set(out[-1]) == {"left", "right"}
    assert det.stats["handedness_turns"] == 1
    np.testing.assert_allclose(out[-1]["left"]["uv"], truth[-1][1], atol=DOT_TOL)   # the true left hand
    for kwargs in ({"opposite_hands": None}, {"opposite_hands": 1.1}):
        det, out = sides(**kwargs)
        assert set(out[-1]) == {"right"} and len(det.tracks) == 2 and det.stats["handedness_turns"] == 0


def test_a_second_hand_beside_a_tracked_one_is_a_new_track_not_the_tracks_own():
    """Clapping: hand B's centre lies inside tracked hand A's crop (1.5x its joint box). The
    finder's box on A is A's; the box on B starts a new track, and A is not re-seeded."""
    from handmocap.perception.crops import square_box
    a = canonical_hand((250, 300), 120)
    box_a = square_box(a)
    b = a + (0.65 * (box_a[2] - box_a[0]), 0.0)                # joint boxes' IoU 0.21
    box_b = square_box(b)
    finder = ScriptedFinder([FoundHand(box_a, 0.9, 0.9), FoundHand(box_b, 0.8, 0.1)])
    det = HandDetector(FakeDetNet(), finder)
    track = Track(0, crop_for_joints(a), uv=a)
    det.tracks, det.next_id = [track], 1
    assert det._covers(track.crop, box_b)                      # what used to swallow the second hand
    new = det._find(np.zeros((H, W, 3), np.uint8))
    assert [t.track_id for t in new] == [1] and det.stats["reseeds"] == 0
    np.testing.assert_allclose(new[0].crop.box, crop_for_joints(b, mirrored=True).box, atol=1)
    assert track.uv is a                                       # A keeps its joints and crop


def test_dropping_a_duplicate_track_makes_the_finder_look_again_next_frame():
    det = detector(redetect_every=10)
    frames, _ = two_hand_frames(2)
    det.process(frames[0])
    det.process(frames[1])
    assert not det._should_find()
    hand = next(h for h in det.process(frames[1]) if h["handedness"] == "right")
    twice = [hand, dict(hand, track_id=99, score=0.5)]
    det.tracks.append(Track(99, det.tracks[0].crop))
    det.lost_last_frame = False
    assert [h["track_id"] for h in det._drop_duplicates(twice)] == [hand["track_id"]]
    assert det._should_find()


def test_a_found_hand_evicts_the_track_detnet_believes_less_when_every_slot_is_taken():
    """max_hands 1: a track born on a partial hand (3 joints missing: mean heatmap peak
    0.86) holds the only slot when the whole hand (peak 1.0) appears. At the finder's next
    check the hand takes the slot when its peak beats the track's by evict_margin, never
    when eviction is off or the margin is larger than the difference; where no peak could
    (the track's peak plus the margin above 1), the found hand costs no DetNet read."""
    decoy, hand = canonical_hand((150, 330), 160), canonical_hand((500, 330), 120)
    frames = [draw(np.zeros((480, 640, 3), np.uint8), decoy[:18]) for _ in range(3)]
    frames += [draw(draw(np.zeros((480, 640, 3), np.uint8), decoy[:18]), hand) for _ in range(6)]

    def last_hands(**kwargs):
        det = HandDetector(FakeDetNet(), FakeFinder(), max_hands=1, birth_confidence=0.0, redetect_every=5,
                           redetect_every_full=5, **kwargs)
        hands = [det.process(f) for f in frames][-1]
        assert len(hands) == 1
        return det, hands[0]

    det, evicted = last_hands(evict_margin=0.1)
    assert det.stats["evictions"] == 1 and evicted["track_id"] == 1
    assert np.abs(evicted["uv"] - hand).max() < 3 * DOT_TOL
    for kept in (last_hands(evict_margin=None)[1], last_hands(evict_margin=0.2)[1]):
        assert kept["track_id"] == 0 and np.linalg.norm(kept["uv"].mean(0) - decoy[:18].mean(0)) < 40
    # 0.86 + 0.2 is above 1, which no heatmap peak exceeds: the found hand is not even read
    assert last_hands(evict_margin=0.2)[0].stats["crops"] == last_hands(evict_margin=None)[0].stats["crops"]
    assert last_hands(evict_margin=0.1)[0].stats["crops"] > last_hands(evict_margin=None)[0].stats["crops"]


def test_a_fallback_finder_is_tried_only_where_the_first_gave_no_track():
    frames, truth = two_hand_frames(3)

    class Blind(FakeFinder):
        def find(self, image_bgr, threshold=None, max_hands=2):
            self.calls += 1
            return []
    blind, fallback = Blind(), FakeFinder()
    detector = HandDetector(FakeDetNet(), blind, fallback=fallback, redetect_every=100, reseed_iou=0)
    assert [len(detector.process(f)) for f in frames] == [2, 2, 2]
    assert blind.calls == fallback.calls == detector.stats["fallback_runs"] == 1   # then tracked
    assert len(HandDetector(FakeDetNet(), Blind()).process(frames[0])) == 0


def test_the_centre_fallback_finds_a_close_up_hand_the_finder_misses_if_detnet_believes_it():
    """A photo whose hand fills the frame, which the finder misses: the centre square is
    tried; a track from it is born only from centre_confidence on, even with
    birth_confidence 0 (a photo's setting)."""
    frame = draw(np.zeros((256, 256, 3), np.uint8), canonical_hand((152, 188), 120))

    class Blind(FakeFinder):
        def find(self, image_bgr, threshold=None, max_hands=2):
            return []

    def hands(detnet, **kwargs):
        return HandDetector(detnet, Blind(), birth_confidence=0.0, **kwargs).process(frame)

    assert len(hands(FakeDetNet())) == 0
    found = hands(FakeDetNet(), fallback=CENTRE)
    assert len(found) == 1 and np.abs(found[0]["uv"] - canonical_hand((152, 188), 120)).max() < 3 * DOT_TOL
    assert len(hands(DimDetNet([0.25]), fallback=CENTRE)) == 0                      # below centre_confidence 0.3
    assert len(hands(DimDetNet([0.25]), fallback=CENTRE, centre_confidence=0.2)) == 1


def test_a_new_tracks_crop_is_recut_once_from_its_own_first_prediction():
    frames, _ = two_hand_frames(1)
    net = FakeDetNet()
    HandDetector(net, FakeFinder()).process(frames[0])
    assert net.calls == 1 + 1 + 1                  # the crops, their three other quarter turns, the re-cut


@pytest.mark.parametrize("right,angle", [(True, 0.0), (False, 0.0), (True, 2.2), (False, -0.6)])
def test_test_time_crops_read_a_new_hand_on_variants_of_its_crop_and_map_them_back(right, angle):
    """test_time_crops=K: a new track's reading is the median over its crop and K variants
    (larger, smaller, turned), each mapped back through its own crop: 2D in frame px and 3D
    in the frame camera's axes come out where the hand is, mirrored and turned crops too."""
    uv_true = turned_hand((320, 240), 150, angle, right)
    frame = draw(np.zeros((H, W, 3), np.uint8), uv_true)
    plain = HandDetector(FakeDetNet(), FakeFinder(), birth_confidence=0.0)
    base = plain.process(frame)
    det = HandDetector(FakeDetNet(), FakeFinder(), birth_confidence=0.0, test_time_crops=4)
    out = det.process(frame)
    assert det.stats["crops"] == plain.stats["crops"] + 4
    assert [h["handedness"] for h in out] == [h["handedness"] for h in base]
    np.testing.assert_allclose(out[0]["uv"], np.round(uv_true), atol=DOT_TOL)
    # the fake DetNet lifts each crop's 2D to 3D: back in frame axes, the frame's 2D lifted
    lifted = normalize_joints(np.concatenate([out[0]["uv"], np.zeros((21, 1))], 1))
    np.testing.assert_allclose(out[0]["xyz_rel"], lifted, atol=0.03)
    plain.process(frame), det.process(frame)                # a tracked hand is read on its own crop only
    assert det.stats["crops"] == plain.stats["crops"] + 4


def test_test_time_crops_halve_the_scatter_of_a_noisy_reading():
    """A DetNet whose 2D answer scatters by 3 crop px per joint, independently per crop:
    the median over the crop and 4 variants is nearer the hand than the crop's reading."""
    class NoisyDetNet(FakeDetNet):
        def __init__(self):
            super().__init__()
            self.rng = np.random.default_rng(0)

        def __call__(self, crops_rgb):
            out = super().__call__(crops_rgb)
            out["uv"] = out["uv"] + self.rng.normal(0, 3.0, out["uv"].shape).astype(np.float32)
            return out
    uv_true = np.round(canonical_hand((320, 240), 150))
    frame = draw(np.zeros((H, W, 3), np.uint8), uv_true)
    errors = {}
    for k in (0, 4):
        det = HandDetector(NoisyDetNet(), FakeFinder(), test_time_crops=k, birth_confidence=0.0)
        err = []
        for _ in range(40):
            det.reset()
            err.append(np.linalg.norm(det.process(frame)[0]["uv"] - uv_true, axis=1).mean())
        errors[k] = np.mean(err)
    assert errors[4] < 0.75 * errors[0], errors
    with pytest.raises(ValueError, match="test_time_crops"):
        HandDetector(FakeDetNet(), FakeFinder(), test_time_crops=99)


def test_tracked_test_time_crops_read_every_tracked_hand_on_variants_on_every_frame():
    uv_true = turned_hand((320, 240), 150, 0.4, False)
    frame = draw(np.zeros((H, W, 3), np.uint8), uv_true)
    plain = HandDetector(FakeDetNet(), FakeFinder(), mirror_vote_every=0)
    det = HandDetector(FakeDetNet(), FakeFinder(), mirror_vote_every=0, tracked_test_time_crops=2)
    plain.process(frame), det.process(frame)
    assert det.stats["crops"] == plain.stats["crops"]       # a new track: test_time_crops' business
    for _ in range(3):
        base, out = plain.process(frame), det.process(frame)
        np.testing.assert_allclose(out[0]["uv"], np.round(uv_true), atol=DOT_TOL)
        np.testing.assert_allclose(out[0]["xyz_rel"], base[0]["xyz_rel"], atol=0.03)
    assert det.stats["crops"] == plain.stats["crops"] + 3 * 2
    with pytest.raises(ValueError, match="tracked_test_time_crops"):
        HandDetector(FakeDetNet(), FakeFinder(), tracked_test_time_crops=-1)


def test_second_look_reads_a_hand_again_when_its_size_jumps():
    """second_look=f: a tracked hand whose joints' box changed size by more than f since the
    last frame is read again on `second_look_crops` variants of its crop; a steady hand is read once."""
    steady = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((320, 260), 110))
    bigger = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((320, 260), 135))
    det = HandDetector(FakeDetNet(), FakeFinder(), mirror_vote_every=0, second_look=0.15, second_look_crops=3)
    plain = HandDetector(FakeDetNet(), FakeFinder(), mirror_vote_every=0, second_look=0)
    for frame in (steady, steady, steady, bigger, bigger):
        out, base = det.process(frame), plain.process(frame)
        np.testing.assert_allclose(out[0]["uv"], base[0]["uv"], atol=DOT_TOL)    # the median of good readings
    assert det.stats["second_looks"] == 1 and det.stats["crops"] == plain.stats["crops"] + 3


def test_crop_and_frame_camera_axes_are_inverse_for_mirrored_and_turned_crops():
    from handmocap.perception.crops import crop_to_frame_xyz, frame_to_crop_xyz
    xyz = np.random.default_rng(5).normal(size=(21, 3))
    for mirrored in (False, True):
        for angle in (0.0, 0.4, -2.0):
            crop = CropTransform.around((300, 200), 150, mirrored=mirrored, angle=angle)
            np.testing.assert_allclose(frame_to_crop_xyz(crop, crop_to_frame_xyz(crop, xyz)), xyz, atol=1e-12)


def test_two_tracks_on_one_box_are_one_hand_and_the_surer_is_kept():
    """One hand twice (joints a few px apart), or two hands clasped in one box: one track, the
    higher score's (telling clasped hands apart by their joints was tried: docs/models_history.md)."""
    from handmocap.perception.crops import CropTransform
    from handmocap.perception.tracks import Track
    right = canonical_hand((300, 300), 150)
    left = right.copy()                                           # clasped: the same box, other joints
    left[:, 0] = right[:, 0].min() + right[:, 0].max() - right[:, 0]
    def hand(tid, uv, score):
        return {"track_id": tid, "score": score, "uv": uv.astype(np.float32)}
    d = HandDetector(FakeDetNet(), FakeFinder())
    d.tracks = [Track(i, CropTransform.around(np.array([300.0, 300.0]), 200.0)) for i in range(3)]
    assert [h["track_id"] for h in d._drop_duplicates([hand(0, right, 0.9), hand(1, left, 0.8)])] == [0]
    assert [h["track_id"] for h in d._drop_duplicates([hand(0, right, 0.8), hand(2, right + 3.0, 0.9)])] == [2]


def test_detector_node_params_take_null_and_booleans_as_the_class_does():
    from handmocap.nodes.detector import PARAMS, TUNABLE, setting
    assert "upright_step" in TUNABLE and "evict_margin" in TUNABLE
    assert setting("evict_margin", None) is None                # null: never evict
    assert setting("evict_margin", 1) == 1.0 and isinstance(setting("evict_margin", 1), float)
    assert setting("max_hands", 1.0) == 1 and isinstance(setting("max_hands", 1.0), int)
    assert setting("upright_step", 0) == 0.0 and setting("upright_step", None) is None
    assert isinstance(PARAMS["upright_step"], float)
    with pytest.raises(ValueError, match="max_hands"):
        setting("max_hands", "two")
    with pytest.raises(ValueError, match="finder_threshold: expected a number, got null"):
        setting("finder_threshold", None)             # the class has no "off" for it
    assert setting("finder_threshold", 0.2) == 0.2
    assert setting("handedness", "right") == "right" and setting("handedness", None) is None
    with pytest.raises(ValueError, match="handedness"):
        setting("handedness", "Rigth")
    # the launcher's check runs the settings' own ranges too, before any process starts
    from handmocap.nodes.detector import check_params
    with pytest.raises(ValueError, match="detector param test_time_crops must be 0..6"):
        check_params({"test_time_crops": 99})
    with pytest.raises(ValueError, match="detector param smooth_min_cutoff and smooth_beta"):
        check_params({"smooth_beta": -1.0})
    check_params({"test_time_crops": 4, "handedness": "left"})
    assert setting("turn_by", "palm") == "palm"              # a word the settings check themselves
    with pytest.raises(ValueError, match="turn_by: expected a word"):
        setting("turn_by", 2)
    with pytest.raises(ValueError, match="turn_by must be one of wrist_knuckle, palm"):
        check_params({"turn_by": "thumb"})


def test_one_settings_dataclass_for_the_detector_the_node_and_handeval():
    """DetectorSettings is where HandDetector's settings and defaults live: the detector node's
    params and `handeval --set` read it (no signature introspection), and a misspelt setting
    is a TypeError naming it."""
    import dataclasses

    from handmocap.nodes import detector as node
    from handmocap.perception.detector import DetectorSettings, HandDetector
    from handmocap.training.eval_cli import detector_settings
    defaults = DetectorSettings()
    assert all(node.PARAMS[k] == getattr(defaults, k) for k in node.TUNABLE)
    assert detector_settings(["second_look=0.2", "handedness=left"]) == {"second_look": 0.2, "handedness": "left"}
    with pytest.raises(ValueError, match="KEY one of"):
        detector_settings(["secnd_look=0.2"])
    d = HandDetector(None, settings=DetectorSettings(max_hands=1), upright_step=None)
    assert (d.max_hands, d.upright_step, d.settings.redetect_every) == (1, None, defaults.redetect_every)
    with pytest.raises(TypeError, match="no setting max_hand"):
        HandDetector(None, max_hand=1)
    assert {f.name for f in dataclasses.fields(DetectorSettings)} >= set(node.TUNABLE)


class ShakyDetNet(FakeDetNet):
    """FakeDetNet whose 2D read-out (`uv`, not the heatmap peaks the track follows) shakes by
    seeded Gaussian noise of `px` crop px: DetNet's frame-to-frame jitter."""

    def __init__(self, px, seed=0):
        super().__init__()
        self.px, self.rng = px, np.random.default_rng(seed)

    def __call__(self, crops_rgb):
        out = super().__call__(crops_rgb)
        out["uv_peak"] = out["uv"].copy()
        out["uv"] = out["uv"] + self.rng.normal(0.0, self.px, out["uv"].shape).astype(np.float32)
        return out


def test_the_published_joints_of_a_still_hand_shake_less_and_a_moving_hand_is_followed():
    """smooth_min_cutoff / smooth_beta: a One Euro filter per track on the published 2D joints,
    on the times process() is given: a still hand's shake drops; a hand moving 8 px a frame at
    30 fps is followed within a few px; off (None), the read-out is published as it is."""
    still = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160))
    shake = {}
    for smooth in (None, 2.0):
        det = HandDetector(ShakyDetNet(2.0), FakeFinder(), smooth_min_cutoff=smooth, redetect_every=1000)
        uv = np.array([det.process(still, i / 30)[0]["uv"] for i in range(60)])
        shake[smooth] = np.linalg.norm(uv[12:] - 2 * uv[11:-1] + uv[10:-2], axis=-1).mean()
    assert shake[2.0] < 0.5 * shake[None]
    det = HandDetector(ShakyDetNet(0.0), FakeFinder(), redetect_every=1000)       # the default filter
    for i in range(40):
        truth = np.round(canonical_hand((150 + 8 * i, 300), 150))
        hands = det.process(draw(np.zeros((H, W, 3), np.uint8), truth), i / 30)
    assert np.abs(hands[0]["uv"] - truth).max() < 4.0
    # the same frames 1/3 s apart: the filter runs on the times given, and lags less
    slow = HandDetector(ShakyDetNet(0.0), FakeFinder(), redetect_every=1000)
    for i in range(40):
        truth = np.round(canonical_hand((150 + 8 * i, 300), 150))
        slow_hands = slow.process(draw(np.zeros((H, W, 3), np.uint8), truth), i / 3)
    assert np.abs(slow_hands[0]["uv"] - truth).max() < np.abs(hands[0]["uv"] - truth).max()
    with pytest.raises(ValueError, match="smooth"):
        HandDetector(FakeDetNet(), FakeFinder(), smooth_min_cutoff=-1.0)


class FakePair:
    """DetNetRunner with a side network: keypoints from `keypoints`, the handedness from `side`
    (both FakeDetNets); read_side=False skips `side` and gives NaN handedness."""

    def __init__(self, keypoints, side):
        self.keypoints, self.side = keypoints, side
        self.side_crops, self.keypoint_crops = [], []   # crops each network read, per call

    def __call__(self, crops_rgb, read_side=True, side_only=0):
        out = self.keypoints(crops_rgb[:len(crops_rgb) - side_only])
        self.keypoint_crops.append(len(crops_rgb) - side_only)
        self.side_crops.append(len(crops_rgb) if read_side else 0)
        out["handedness"] = self.side(crops_rgb)["handedness"] if read_side else np.full(len(crops_rgb), np.nan)
        return out


def test_side_every_reads_the_side_network_on_births_and_mirror_votes_only():
    """With a side network and side_every=6 (= mirror_vote_every), a tracked hand's side is
    read on its first crops and on every 6th frame (both readings), and its side stays the
    side network's, not the keypoint network's (biased the other way); the keypoint network
    never reads a mirror vote's flipped crop."""
    frame = draw(np.zeros((H, W, 3), np.uint8), canonical_hand((250, 300), 160, right=False))
    for every, reads in ((None, 13), (6, 3)):
        pair = FakePair(FakeDetNet(right_bias=6.0), FakeDetNet())
        det = HandDetector(pair, FakeFinder(), finder_handedness=0.0, mirror_vote_every=6, side_every=every,
                           upright_step=None)
        sides = [h["handedness"] for _ in range(13) for h in det.process(frame)]
        assert sides == ["left"] * 13, every
        # a birth reads its crop twice (turn, refine); then one frame in `every` (two crops: the vote)
        read_frames = sum(n > 0 for n in pair.side_crops)
        assert read_frames == reads + 1, (every, pair.side_crops)
        # the flipped crop of a mirror vote goes to the side network alone
        assert all(k == 1 for k in pair.keypoint_crops) and max(pair.side_crops) == 2
        assert det.tracks[0].right_logit < 0 and det.tracks[0].samples > 0


def test_half_of_a_calls_crops_are_cut_on_detnets_second_thread_and_the_hands_are_the_same(monkeypatch):
    """With DetNet's second thread (`beside`), the later half of two or more crops read at once
    (a new track's turns, a second look) is cut there while the caller cuts the first half;
    the hands are the same to the bit as with every crop cut and read in turn."""
    import threading
    from handmocap.perception.crops import CropTransform
    from handmocap.runtime.frames import read_video
    frames = [f for _, f in zip(range(20), read_video(str(CLIP)))]
    cut, threads = CropTransform.cut, []

    def recorded(self, image):
        threads.append(threading.current_thread().name)
        return cut(self, image)
    monkeypatch.setattr(CropTransform, "cut", recorded)
    hands = {}
    for beside in (True, False):
        det = HandDetector.load(max_hands=2, finder_beside=False)
        det.detnet.beside = beside
        threads.clear()
        hands[beside] = [det.process(f) for f in frames]
        assert any(t.startswith("detnet-beside") for t in threads) == beside
    for a, b in zip(hands[True], hands[False]):
        assert [h["track_id"] for h in a] == [h["track_id"] for h in b] and a
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x["uv"], y["uv"])
            np.testing.assert_array_equal(x["xyz_rel"], y["xyz_rel"])


def test_the_finder_runs_beside_the_tracked_crops_on_a_thread_of_its_own():
    """finder_beside (the default): with a hand tracked, the finder's periodic run goes on the
    detector's "finder" thread while DetNet reads the same frame's crops, and the hands come out
    as with the finder in turn (the same tracks, joints within a hundredth of a pixel); with no
    track it runs on the frame first."""
    import threading
    from handmocap.runtime.frames import read_video
    frames = [f for _, f in zip(range(40), read_video(str(CLIP)))]
    hands = {}
    for beside in (True, False):
        det = HandDetector.load(max_hands=2, finder_beside=beside)
        threads, run = [], det.finder.find

        def recorded(*args, run=run, threads=threads):
            threads.append(threading.current_thread().name)
            return run(*args)
        det.finder.find = recorded
        hands[beside] = [det.process(f) for f in frames]
        assert det.stats["finder_runs"] >= 4
        on_thread = [t.startswith("finder") for t in threads]
        assert (on_thread[0], any(on_thread)) == (False, beside)     # the first, with no track yet: on the frame
    assert [len(h) for h in hands[True]] == [len(h) for h in hands[False]] and min(map(len, hands[True])) == 1
    for a, b in zip(hands[True], hands[False]):
        assert [h["track_id"] for h in a] == [h["track_id"] for h in b]
        assert max(np.abs(x["uv"] - y["uv"]).max() for x, y in zip(a, b)) < 0.01


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs an affinity call and two CPUs")
def test_helper_threads_stay_on_one_cpu_and_the_frames_thread_off_it_only_while_it_reads():
    """pin_threads: DetNet's second thread runs on the helper CPU (onnx_models.cpu_split); the
    thread calling process() is kept off it during the call, and its CPUs are as before after
    it (a process it starts later inherits no pinning)."""
    from handmocap.perception.onnx_models import cpu_split
    caller_cpus, helper_cpus = cpu_split()
    assert helper_cpus and not caller_cpus & helper_cpus
    before = os.sched_getaffinity(0)
    seen = {}

    class BesideDetNet(FakeDetNet):
        beside, pin_helper = True, True

        def __call__(self, crops_rgb):
            seen["caller"] = os.sched_getaffinity(0)
            seen["helper"] = self.second_thread().submit(os.sched_getaffinity, 0).result()
            return super().__call__(crops_rgb)

        def second_thread(self):
            if not hasattr(self, "_pool"):
                from concurrent.futures import ThreadPoolExecutor
                from handmocap.perception.onnx_models import keep_on_helper_cpu
                self._pool = ThreadPoolExecutor(1, initializer=keep_on_helper_cpu if self.pin_helper else None)
            return self._pool

    frames, _ = two_hand_frames(3)
    det = HandDetector(BesideDetNet(), FakeFinder(), smooth_min_cutoff=None)
    for f in frames:
        det.process(f)
    assert seen["caller"] == set(caller_cpus) and seen["helper"] == set(helper_cpus)
    assert os.sched_getaffinity(0) == before
    seen.clear()
    det = HandDetector(BesideDetNet(), FakeFinder(), smooth_min_cutoff=None, pin_threads=False)
    det.process(frames[0])
    assert seen["caller"] == before and seen["helper"] == before


@pytest.mark.parametrize("param, wrong, words", [
    ("finder", "iknet.onnx", "hand finder model models/iknet.onnx does not take a frame"),
    ("grey_finder", "iknet.onnx", "hand finder model models/iknet.onnx does not take a frame"),
    ("grey_detnet", "finder.onnx", "models/finder.onnx is not a DetNet"),
    ("detnet", "iknet.onnx", "models/iknet.onnx is not a DetNet"),
])
def test_the_detector_node_refuses_a_model_file_that_is_another_network_at_start(param, wrong, words, run_dir):
    """A file that exists and loads but is not the network its param names fails the node at its
    start (exit 2, one error line naming the file), not on the first frame that would use it: a
    grey-frame network included, which a colour camera may never reach."""
    r = subprocess.run([sys.executable, "-m", "nodes.detector", f"{param}:=models/{wrong}"], cwd=ROOT,
                       env=graph_env(run_dir), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr, r.stderr[-2000:]


def test_a_hand_entering_from_the_edge_is_kept_by_its_joints_inside():
    """Session 62: a pianist's hand seen from above enters from the frame's bottom; DetNet reads
    its unseen wrist far below the frame, the joints' box centre crosses the edge, and the track
    ended while the fingers were in view. `edge_joints` keeps it while that many joints are inside."""
    h, w = 540, 960
    uv = np.stack([np.full(21, 400.0), np.linspace(300.0, 800.0, 21)], axis=1)   # centre y 550 > h
    inside = int((uv[:, 1] < h).sum())
    assert not HandDetector._plausible(uv, (h, w, 3))                       # the centre alone decides
    assert HandDetector._plausible(uv, (h, w, 3), edge_joints=inside)
    assert not HandDetector._plausible(uv, (h, w, 3), edge_joints=inside + 1)
    gone = uv + [0.0, 600.0]                                                # every joint below the frame
    assert not HandDetector._plausible(gone, (h, w, 3), edge_joints=1)
    assert not HandDetector._plausible(uv * 10, (h, w, 3), edge_joints=1)   # wider than twice the frame
    with pytest.raises(ValueError, match="edge_joints"):
        DetectorSettings(edge_joints=0)
