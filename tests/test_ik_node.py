"""The ik node: its maths in-process (mirroring, translation, every HandPose field), the
per-track smoothing, and the node in a real graph."""
import numpy as np
import pytest

from conftest import handlaunch
from handmocap.perception import camera_info
from handmocap.runtime import codec
from handmocap.runtime.bag import iter_messages
from handmocap.perception.hand_model import HandModel
from handmocap.perception.ik_solver import IKSolver
from handmocap.training.pose_data import PoseSampler
from handmocap.perception.rotations import mirror_points, quat_angle_between
from handmocap.perception.skeleton import normalize_joints

from handmocap.perception import pose as ik
MODEL = HandModel.load()
SOLVER = IKSolver.load()
W, H = 640, 480
K = camera_info.default_K(W, H)
FIELDS = {"xyz": (21, 3), "root": (3,), "quat": (21, 4), "pose": (16, 3), "beta": (10,), "uv": (21, 2)}


def synthetic_hands(n, seed, handedness="right", depth=0.6):
    """n HandKeypoints hands of known pose and shape, seen by camera K; the true joints in
    metres (camera frame) and beta. A left hand is the mirror image of the right one."""
    d = PoseSampler(MODEL).sample(n, np.random.default_rng(seed))
    _, joints = MODEL.forward(d["quats"], d["beta"])
    xyz = joints - joints[:, 9:10] + np.array([0.03, -0.02, depth])
    if handedness == "left":
        xyz = mirror_points(xyz)
    uv = (xyz @ K.T)[..., :2] / xyz[..., 2:]
    hands = [{"track_id": 3, "handedness": handedness, "score": 0.9,
              "bbox": np.concatenate([u.min(0), u.max(0)]).astype(np.float32), "uv": u.astype(np.float32),
              "confidence": np.ones(21, np.float32), "xyz_rel": normalize_joints(x).astype(np.float32)}
             for u, x in zip(uv, xyz)]
    return hands, xyz, d


def test_pose_has_every_field_and_recovers_the_hand():
    hands, xyz, d = synthetic_hands(20, 0)
    errors, root_errors = [], []
    for hand, true_xyz, beta in zip(hands, xyz, d["beta"]):
        out = ik.pose_from_keypoints(hand, K, MODEL.rest_joints(beta), SOLVER, MODEL, beta)
        for name, shape in FIELDS.items():
            assert out[name].shape == shape and out[name].dtype == np.float32, name
        assert out["track_id"] == 3 and out["handedness"] == "right" and out["score"] == pytest.approx(0.9)
        assert isinstance(out["translation_valid"], bool)
        np.testing.assert_allclose(out["xyz"][9], out["root"], atol=1e-6)
        codec.encode({"header": codec.header(0), "hands": [out]}, "HandPose")      # schema-valid
        # xyz, quat, pose and beta agree: the model posed by pose (or quat) at beta is xyz
        for pose in (out["pose"], out["quat"]):
            _, joints = MODEL.forward(pose, beta)
            np.testing.assert_allclose(joints - joints[9] + out["root"], out["xyz"], atol=1e-5)
        errors.append(np.linalg.norm(out["xyz"] - true_xyz, axis=-1).mean())
        root_errors.append(np.linalg.norm(out["root"] - true_xyz[9]))
    assert np.median(root_errors) < 0.03, root_errors       # Eq. 5 with IKNet's wrist depth, 0.6 m away
    assert np.median(errors) < 0.04, errors


def test_left_hand_is_solved_in_the_right_model_and_mirrored_back():
    right, _, d = synthetic_hands(5, 1, "right")
    left, true_left, _ = synthetic_hands(5, 1, "left")
    for r, l, true_xyz, beta in zip(right, left, true_left, d["beta"]):
        out_r = ik.pose_from_keypoints(r, K, None, SOLVER, MODEL, beta)
        out_l = ik.pose_from_keypoints(l, K, None, SOLVER, MODEL, beta)
        assert out_l["handedness"] == "left"
        # right-model rotations: the two hands' joints for IKNet mirror each other to 1e-7 (their
        # x, y come through K's rays), which can move the int8 network's input over a rounding
        # step: 0.3 degrees at most here, hence 1
        assert np.degrees(quat_angle_between(out_l["quat"], out_r["quat"])).max() < 1.0
        np.testing.assert_allclose(out_l["pose"], out_r["pose"], atol=0.02)
        # the hand as seen: mirrored positions (K's principal point is at the image centre)
        np.testing.assert_allclose(out_l["xyz"], mirror_points(out_r["xyz"]), atol=1e-3)
        _, joints = MODEL.forward(out_l["quat"], beta, handedness="left")
        np.testing.assert_allclose(joints - joints[9] + out_l["root"], out_l["xyz"], atol=1e-5)
        assert np.linalg.norm(out_l["xyz"] - true_xyz, axis=-1).mean() < 0.05


def test_estimator_solves_every_hand_of_a_frame_in_one_batch_as_it_would_one_by_one():
    """Two hands of different people and sides in one message: one IKNet run, one clamp and
    one pass of the fields (hands_pose_fields) for both give each hand exactly what it gets
    alone (the int8 IKNet is statically quantized), with each track's own shape."""
    right, _, d = synthetic_hands(2, 5, "right")
    left, _, _ = synthetic_hands(2, 6, "left")
    pair = [{**right[0], "track_id": 1}, {**left[1], "track_id": 2}]
    shapes = [{"track_id": tid, "beta": d["beta"][i], "rest_xyz": normalize_joints(MODEL.rest_joints(d["beta"][i]))}
              for i, tid in enumerate((1, 2))]
    together = ik.PoseEstimator(SOLVER, MODEL, smooth=False)
    together.set_shapes(shapes)
    both = together.update(pair, K, 0.0)
    for hand, out in zip(pair, both):
        alone = ik.PoseEstimator(SOLVER, MODEL, smooth=False)
        alone.set_shapes(shapes)
        (single,) = alone.update([hand], K, 0.0)
        assert single["track_id"] == out["track_id"] and single["handedness"] == out["handedness"]
        for field in ("quat", "pose", "xyz", "root", "beta"):
            np.testing.assert_allclose(out[field], single[field], atol=1e-6, err_msg=field)


def test_estimator_uses_track_shapes_smooths_and_resets_lost_tracks():
    hands, _, d = synthetic_hands(1, 2)
    hand = hands[0]
    rng = np.random.default_rng(3)
    jittered = [{**hand, "uv": hand["uv"] + rng.normal(0, 2.0, (21, 2)).astype(np.float32),
                 "xyz_rel": hand["xyz_rel"] + rng.normal(0, 0.02, (21, 3)).astype(np.float32)} for _ in range(60)]
    raw = ik.PoseEstimator(SOLVER, MODEL, smooth=False)
    smooth = ik.PoseEstimator(SOLVER, MODEL)
    beta = d["beta"][0]
    for est in (raw, smooth):
        est.set_shapes([{"track_id": 3, "beta": beta, "rest_xyz": normalize_joints(MODEL.rest_joints(beta))}])
    outs = {name: [est.update([h], K, i / 30.0)[0] for i, h in enumerate(jittered)]
            for name, est in (("raw", raw), ("smooth", smooth))}
    # the track's shape, at the size of the default hand length (bone ratios cannot show size)
    sized = MODEL.sized(beta, ik.PoseSettings().hand_length)
    np.testing.assert_allclose(outs["smooth"][0]["beta"], sized.astype(np.float32), rtol=1e-6)
    assert np.all(np.delete(sized, MODEL.beta_names.index("hand_size")) == np.delete(beta, 0))
    for field in ("root", "quat"):
        jitter = {k: np.abs(np.diff([o[field] for o in v[10:]], axis=0)).mean() for k, v in outs.items()}
        assert jitter["smooth"] < 0.5 * jitter["raw"], (field, jitter)
    # the track disappears for a frame: its filters start afresh (first output = unsmoothed)
    assert smooth.update([], K, 2.1) == []
    first = smooth.update([jittered[5]], K, 2.2)[0]
    np.testing.assert_allclose(first["root"], outs["raw"][5]["root"], atol=1e-6)
    # a hand with missing joints is skipped, the others are solved
    broken = {**hand, "track_id": 4, "xyz_rel": np.full((21, 3), np.nan, np.float32)}
    assert [o["track_id"] for o in smooth.update([broken, hand], K, 2.3)] == [3]


def test_ik_node_in_a_graph(tmp_path, run_dir):
    """A publishing test node (synthetic hands projected with a known K, and /camera/info)
    -> ik -> recorder, under handlaunch: one /hand/pose per /hand/keypoints, same stamps."""
    out = tmp_path / "pose.mcap"
    lf = tmp_path / "g.yaml"
    lf.write_text(f"""
nodes:
  source: {{node: graphnodes.keypoints_source, params: {{frames: 20, handedness: left, track_id: 8}}, required: true}}
  ik: {{node: ik, required: true}}
  recorder: {{node: recorder, params: {{output: {out}, topics: [/hand/keypoints, /hand/pose]}}, required: true}}
  meshes: {{node: recorder, params: {{output: {tmp_path / "mesh.mcap"}, topics: [/hand/mesh]}}, required: true}}
""")
    r = handlaunch([lf], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    got = {"/hand/keypoints": [], "/hand/pose": []}
    for topic, type_name, payload, _ in iter_messages(out):
        got[topic].append(codec.decode(payload, type_name))
    sent, poses = got["/hand/keypoints"], got["/hand/pose"]
    assert len(sent) == 20 and len(poses) == 20, r.stdout                 # one pose per keypoints message
    assert sorted(m["header"]["stamp_ns"] for m in poses) == sorted(m["header"]["stamp_ns"] for m in sent)
    for m in poses:
        (h,) = m["hands"]
        for name, shape in FIELDS.items():
            assert h[name].shape == shape and h[name].dtype == np.float32, name
        assert h["handedness"] == "left" and h["track_id"] == 8
        assert 0.35 < h["root"][2] < 0.7                                   # the source's hands are 0.5 m away
    # /hand/mesh, asked for by name: one per pose, the mesh of its hand, the faces once
    meshes = [codec.decode(payload, t) for _, t, payload, _ in iter_messages(tmp_path / "mesh.mcap")]
    assert [m["header"]["stamp_ns"] for m in meshes] == [m["header"]["stamp_ns"] for m in poses]
    assert [("faces" in m) for m in meshes] == [True] + [False] * 19
    np.testing.assert_array_equal(meshes[0]["faces"], MODEL.faces)
    for m, p in zip(meshes, poses):
        (mh,), (ph,) = m["hands"], p["hands"]
        assert (mh["track_id"], mh["handedness"]) == (8, "left")
        vertices, _, joints = ik.hand_mesh(MODEL, ph)
        assert mh["vertices"].shape == vertices.shape and mh["vertices"].dtype == np.float32
        np.testing.assert_allclose(mh["vertices"], vertices, atol=1e-5)
        np.testing.assert_allclose(joints, ph["xyz"], atol=1e-5)               # the mesh sits on the pose


def test_a_topic_is_wanted_only_by_subscribers_that_name_it():
    """Publisher.named_subscribers: the ik node computes /hand/mesh only for those."""
    import functools
    import time

    import zmq
    from handmocap.runtime.bus import Publisher, Subscriber
    ctx = zmq.Context()
    pub = Publisher(ctx, "inproc://named-subscribers")
    everything, named = Subscriber(ctx), Subscriber(ctx)
    try:
        everything.subscribe(None, "all")
        everything.connect("inproc://named-subscribers", "all")

        def settled(read, want):
            deadline = time.monotonic() + 5
            while read() != want and time.monotonic() < deadline:
                time.sleep(0.01)
            return read()
        # the catch-all subscription has arrived (subscriptions reach the publisher asynchronously) ...
        assert settled(lambda: pub.subscriber_count("/hand/mesh"), 1) == 1
        assert pub.named_subscribers("/hand/mesh") == (0, 0)          # ... and does not ask for the mesh
        settled = functools.partial(settled, lambda: pub.named_subscribers("/hand/mesh"))
        named.subscribe("/hand/mesh", "latest")
        named.connect("inproc://named-subscribers", "latest")
        assert settled((1, 1)) == (1, 1)
        named.close()
        assert settled((0, 1)) == (0, 1)              # gone; a later one makes joined 2 (faces again)
    finally:
        everything.close(), pub.close(), ctx.term()


def test_pose_settings_are_declared_once_and_checked_where_declared():
    """PoseSettings' fields are the ik node's params; a bad value is one error naming it, from
    the launcher's check and from PoseEstimator alike; an unknown setting is a TypeError."""
    import dataclasses

    from handmocap.nodes import ik as ik_node
    assert set(ik_node.SETTINGS) == {f.name for f in dataclasses.fields(ik.PoseSettings)} <= set(ik_node.PARAMS)
    for bad, name in (({"rot_min_cutoff": 0}, "rot_min_cutoff"), ({"hand_length": 18}, "hand_length"),
                      ({"smooth": "yes"}, "smooth"), ({"xy_from_keypoints": -1}, "xy_from_keypoints")):
        with pytest.raises(ValueError, match=f"ik param {name}"):
            ik_node.check_params(bad)
        with pytest.raises(ValueError, match=name):
            ik.PoseEstimator(SOLVER, MODEL, **bad)
    with pytest.raises(TypeError, match="no setting smoothing"):
        ik.PoseEstimator(SOLVER, MODEL, smoothing=False)
    assert ik.PoseEstimator(SOLVER, MODEL, hand_length=0.2).settings.hand_length == 0.2
