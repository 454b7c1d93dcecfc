"""The shape node: its estimator in-process, and the node in a real graph."""
import numpy as np

from conftest import handlaunch
from graphnodes.keypoints_source import synthetic_hands
from handmocap.runtime import codec
from handmocap.runtime.bag import iter_messages
from handmocap.perception.hand_model import HandModel
from handmocap.perception.shape import ShapeEstimator
from handmocap.perception.skeleton import normalize_joints

# coefficients that bone ratios can see (hand_size, finger_thickness, wrist_girth cannot: docs/models_history.md)
OBSERVABLE = [1, 2, 3, 4, 5, 6, 9]


def test_estimator_converges_and_forgets_lost_tracks():
    beta = np.array([0.0, 1.0, -1.0, 0.5, 0.0, -0.5, 1.0, 0.0, 0.0, -1.0])
    _, xyz_rel, _ = synthetic_hands(40, beta, seed=1)
    est = ShapeEstimator(HandModel.load())
    for i, x in enumerate(xyz_rel):
        shapes = est.update([{"track_id": 4, "handedness": "left", "xyz_rel": x}], now=i * 0.03)
    (s,) = shapes
    assert s["track_id"] == 4 and s["handedness"] == "left" and s["samples"] == 40
    assert np.abs(s["beta"][OBSERVABLE] - beta[OBSERVABLE]).max() < 0.2
    rest = s["rest_xyz"]
    np.testing.assert_allclose(rest[9], 0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(rest[0] - rest[9]), 1, atol=1e-5)
    np.testing.assert_allclose(rest, normalize_joints(HandModel.load().rest_joints(s["beta"])), atol=1e-5)
    assert est.update([], now=40 * 0.03 + 5.0) == []   # not seen for 5 s: forgotten


def test_shape_node_in_a_graph(tmp_path, run_dir):
    beta = [0.0, 1.5, 0, 0, 0, 0, -1.0, 0, 0, 0]
    bag = tmp_path / "shape.mcap"
    lf = tmp_path / "g.yaml"
    lf.write_text(f"""
nodes:
  source: {{node: graphnodes.keypoints_source, params: {{frames: 30, beta: {beta}}}, required: true}}
  shape: {{node: shape, required: true}}
  recorder: {{node: recorder, params: {{output: {bag}, topics: [/hand/shape]}}}}
""")
    r = handlaunch([lf], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    shapes = [codec.decode(p, t) for _, t, p, _ in iter_messages(bag)]
    assert len(shapes) == 30
    assert [m["shapes"][0]["samples"] for m in shapes] == list(range(1, 31))
    last = shapes[-1]["shapes"][0]["beta"]
    assert abs(last[1] - 1.5) < 0.3 and abs(last[6] + 1.0) < 0.3
