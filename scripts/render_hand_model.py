"""Render the bundled hand model into one picture: shapes and poses.

    python scripts/render_hand_model.py [--out docs/hand_model.png] [--model PATH]

Row 1: the average hand (beta = 0) and beta_k = -2 / +2 on two coefficients.
Row 2: three poses of the average hand (fist, pointing, spread) and the back of the hand.
Needs moderngl with EGL (see handmocap/perception/render.py).
"""
import argparse
from pathlib import Path

import cv2
import numpy as np

from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import named_pose
from handmocap.perception.render import MeshRenderer
from handmocap.perception.rotations import axis_angle_to_matrix

TILE = 360


def place(vertices, joints, view_rotation, depth=0.6):
    """Rotate the model about the middle of the hand and put it in front of the camera."""
    center = joints[[0, 9, 12]].mean(0) * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.03, 0.0])
    return (vertices - center) @ view_rotation.T + np.array([0.0, 0.0, depth])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "docs" / "hand_model.png")
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--coefficients", default="1,9", help="two beta indices shown at -2 and +2")
    args = ap.parse_args()

    model = HandModel.load(args.model)
    renderer = MeshRenderer(TILE, TILE)
    K = np.array([[700.0, 0, TILE / 2], [0, 700.0, TILE / 2], [0, 0, 1]])
    front = axis_angle_to_matrix(np.array([0.0, 0.0, 0.0]))
    three_quarter = axis_angle_to_matrix(np.array([0.0, 0.7, 0.0])) @ axis_angle_to_matrix(np.array([0.35, 0.0, 0.0]))

    tiles = []
    ks = [int(k) for k in args.coefficients.split(",")]
    shapes = [("beta = 0", np.zeros(model.num_betas))]
    for k in ks:
        for s in (-2.0, 2.0):
            beta = np.zeros(model.num_betas)
            beta[k] = s
            shapes.append((f"{model.beta_names[k]} {s:+.0f}", beta))
    for label, beta in shapes:
        v, j = model.forward(None, beta)
        tiles.append((label, place(v, j, front)))
    for name, view in (("fist", three_quarter), ("pointing", three_quarter), ("spread", front)):
        v, j = model.forward(named_pose(name, model))
        tiles.append((name, place(v, model.rest_joints(), view)))
    tiles.append(("back, rest", place(model.forward()[0], model.rest_joints(),
                                           axis_angle_to_matrix(np.array([0.0, np.pi, 0.0])))))

    images = []
    for label, verts in tiles:
        rgb, depth = renderer.render([(verts, model.faces)], K)
        img = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        cv2.putText(img, label, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (40, 40, 40), 1, cv2.LINE_AA)
        images.append(img)
    cols = 5
    while len(images) % cols:
        images.append(np.full_like(images[0], 255))
    rows = [np.concatenate(images[i:i + cols], 1) for i in range(0, len(images), cols)]
    sheet = np.concatenate(rows, 0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), sheet)
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")


if __name__ == "__main__":
    main()
