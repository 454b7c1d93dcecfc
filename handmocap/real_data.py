"""Loaders for the real hand data pack (shared/data/README.md), all in MP joint order.

Every loader returns a list of samples, each a dict:
    image (H,W,3) uint8 RGB · uv (21,2) float32 px · visible (21,) bool ·
    handedness "left" / "right" / None (the hand as it appears in the image) ·
    xyz (21,3) float32 metres camera frame and K (3,3) where the set has them · name str.
Video pseudo-labels (MediaPipe, not ground truth) come as per-frame arrays instead
(`load_pseudo_labels`, `read_video`), since whole clips do not fit in memory as samples.

Splits (README "Use" lines): training may use howiema subject 001 and the MediaPipe
pseudo-labels of TRAIN_VIDEOS. Evaluation only: howiema 040, temugeb_stereo,
cmu_hand_labels_sample, samples/mmpose/*.
"""
import json
from pathlib import Path

import numpy as np

from .pose_data import SHARED_DATA

TRAIN_VIDEOS = (
    "video/webcam/alimostafa_hand.mp4", "video/webcam/huytung228_1hand.mp4",
    "video/webcam/huytung228_hand.mp4", "video/webcam/huytung228_volctl.mp4",
    "video/webcam/lujunwang_hand.mp4", "video/webcam/lujunwang_hand2.mp4",
    "video/webcam/sushensanthush_hand.mp4", "video/dex_retargeting/human_hand_video.mp4",
    "video/tfjs_asl_hand/asl_hand.25fps.mp4",
)
HOWIEMA_TRAIN_SUBJECT, HOWIEMA_EVAL_SUBJECT = "001", "040"
HOWIEMA_HELD_OUT = ("L8", "R8")          # sequences of subject 001 kept for training-side validation
HELD_OUT_TAIL, HELD_OUT_GAP = 0.15, 15   # of every training video: the last 15% validate, 15 frames apart

# RHD: wrist, then each finger tip..base. InterHand: each finger tip..base, wrist last.
RHD_TO_MP = np.array([0, 4, 3, 2, 1, 8, 7, 6, 5, 12, 11, 10, 9, 16, 15, 14, 13, 20, 19, 18, 17])


def interhand_to_mp(offset):
    """Indices into InterHand's 42 joints giving one hand in MP order; offset 0 right, 21 left."""
    o = offset
    return np.array([o + 20, o + 3, o + 2, o + 1, o + 0, o + 7, o + 6, o + 5, o + 4, o + 11, o + 10, o + 9, o + 8,
                     o + 15, o + 14, o + 13, o + 12, o + 19, o + 18, o + 17, o + 16])


def read_image(path):
    """RGB uint8 (H,W,3)."""
    import cv2
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(path)
    return img[..., ::-1].copy()


def _sample(image, uv, visible=None, handedness=None, xyz=None, K=None, name=""):
    uv = np.asarray(uv, np.float32).reshape(21, 2)
    return {"image": image, "uv": uv,
            "visible": np.ones(21, bool) if visible is None else np.asarray(visible, bool).reshape(21),
            "handedness": handedness, "xyz": None if xyz is None else np.asarray(xyz, np.float32).reshape(21, 3),
            "K": None if K is None else np.asarray(K, np.float32).reshape(3, 3), "name": name}


# ------------------------------------------------------------------ videos + MediaPipe pseudo-labels
def video_split(n_frames):
    """(train mask, held-out mask) over a training video's frames: the last HELD_OUT_TAIL
    held out for validation, HELD_OUT_GAP frames between them so that no training frame
    nearly repeats a held-out one."""
    cut = int(round(n_frames * (1 - HELD_OUT_TAIL)))
    idx = np.arange(n_frames)
    return idx < cut - HELD_OUT_GAP, idx >= cut


def load_pseudo_labels(video_path):
    """The `<stem>.mediapipe.npz` beside a video: dict of arrays uv (F,2,21,2), world,
    score (F,2), handedness (F,2) int8 0 Right / 1 Left / -1 empty, found (F,2), fps, size."""
    path = Path(video_path).with_suffix(".mediapipe.npz")
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def read_video(video_path, frames=None):
    """Decoded RGB frames (OpenCV auto-rotation, as the pseudo-labels were made), as a
    generator of (index, image); frames: optional set of indices to keep."""
    import cv2
    cap = cv2.VideoCapture(str(video_path))
    if not cap.isOpened():
        raise FileNotFoundError(video_path)
    i = 0
    try:
        while True:
            ok, bgr = cap.read()
            if not ok:
                break
            if frames is None or i in frames:
                yield i, bgr[..., ::-1].copy()
            i += 1
    finally:
        cap.release()


# ------------------------------------------------------------------ labelled 2D sets
def load_howiema(subject, root=SHARED_DATA):
    """howiema_lstm_pm frames of one subject ("001" train, "040" evaluation): 256x256,
    integer 2D labels; handedness from the sequence name (L/R is the person's real hand,
    unmirrored webcam). name = "<subject>/<seq>/<frame>"."""
    base = Path(root) / "labelled2d" / "howiema_lstm_pm"
    out = []
    for label_file in sorted((base / "label" / subject).glob("*.json")):
        seq = label_file.stem
        labels = json.loads(label_file.read_text())
        for key in sorted(k for k in labels if k != "offset"):
            img_path = base / "frames" / subject / seq / f"{seq[0]}{key}.jpg"
            if img_path.exists():
                out.append(_sample(read_image(img_path), labels[key],
                                   handedness="left" if seq[0] == "L" else "right", name=f"{subject}/{seq}/{key}"))
    return out


def load_cmu_hand_labels_sample(root=SHARED_DATA):
    """16 CMU hand_labels crops (368x368, evaluation only); _l/_r = the person's hand."""
    base = Path(root) / "labelled2d" / "cmu_hand_labels_sample"
    out = []
    for img_path in sorted((base / "data").glob("*.jpg")):
        pts = json.loads((base / "label" / (img_path.stem + ".json")).read_text())["hand_pts_crop"]
        out.append(_sample(read_image(img_path), pts, handedness="left" if img_path.stem.endswith("_l") else "right",
                           name=img_path.stem))
    return out


def _coco(json_path):
    data = json.loads(Path(json_path).read_text())
    images = {im["id"]: im for im in data["images"]}
    return data, [(images[a["image_id"]], a) for a in data["annotations"]]


def load_mmpose(name, root=SHARED_DATA):
    """samples/mmpose/<name> (evaluation / tests only): rhd (with xyz, K), interhand2.6m
    (xyz, K; one sample per valid hand), freihand, panoptic, onehand10k (2D)."""
    base = Path(root) / "samples" / "mmpose" / name
    out = []
    if name == "rhd":
        for im, a in _coco(base / "test_rhd.json")[1]:
            kp = np.asarray(a["keypoints"], np.float32).reshape(21, 3)[RHD_TO_MP]
            cam = im["cam_param"]
            K = [[cam["focal"][0], 0, cam["princpt"][0]], [0, cam["focal"][1], cam["princpt"][1]], [0, 0, 1]]
            xyz = np.asarray(a["joint_cam"], np.float32).reshape(21, 3)[RHD_TO_MP] / 1000.0
            out.append(_sample(read_image(base / im["file_name"]), kp[:, :2], kp[:, 2] > 0, a["hand_type"], xyz, K,
                               im["file_name"]))
    elif name == "interhand2.6m":
        cams = json.loads((base / "test_interhand2.6m_camera.json").read_text())
        joints = json.loads((base / "test_interhand2.6m_joint_3d.json").read_text())
        for im, a in _coco(base / "test_interhand2.6m_data.json")[1]:
            cap, cam_id = str(im["capture"]), str(im["camera"])
            c = cams[cap]
            rot, pos = np.asarray(c["camrot"][cam_id], np.float64), np.asarray(c["campos"][cam_id], np.float64)
            f, p = c["focal"][cam_id], c["princpt"][cam_id]
            K = np.array([[f[0], 0, p[0]], [0, f[1], p[1]], [0, 0, 1]])
            world = np.asarray(joints[cap][str(im["frame_idx"])]["world_coord"], np.float64)
            cam_xyz = (world - pos) @ rot.T
            uv = cam_xyz[:, :2] / cam_xyz[:, 2:] * np.array(f) + np.array(p)
            valid = np.asarray(a["joint_valid"]).reshape(42) > 0
            image = read_image(base / im["file_name"])
            for side, offset in (("right", 0), ("left", 21)):
                idx = interhand_to_mp(offset)
                if valid[idx].sum() >= 11:
                    out.append(_sample(image, uv[idx], valid[idx], side, cam_xyz[idx] / 1000.0, K,
                                       f"{im['file_name']}:{side}"))
    elif name in ("freihand", "panoptic", "onehand10k"):
        for im, a in _coco(base / f"test_{name}.json")[1]:
            kp = np.asarray(a["keypoints"], np.float32).reshape(21, 3)
            side = {"freihand": "right"}.get(name)
            if name == "panoptic":
                side = "left" if Path(im["file_name"]).stem.endswith("_l") else "right"
            out.append(_sample(read_image(base / im["file_name"]), kp[:, :2], kp[:, 2] > 0, side,
                               name=im["file_name"]))
    else:
        raise ValueError(f"unknown mmpose sample set {name!r}")
    return out


def load_temugeb_stereo(root=SHARED_DATA, every=1):
    """Camera-0 frames of the stereo clip (evaluation only) where triangulation exists:
    image (720x720, distorted as recorded), uv = MediaPipe 2D of camera 0 (pseudo-labels),
    xyz = triangulated pseudo-3D in metres, camera-0 frame, K = K0 (use with dist0 =
    sample["dist"]). every: keep every k-th triangulated frame."""
    base = Path(root) / "video" / "temugeb_stereo"
    with np.load(base / "triangulated.npz") as data:
        tri = {k: data[k] for k in data.files}
    labels = load_pseudo_labels(base / "media" / "cam0_test.mp4")
    keep = {int(f): i for i, f in enumerate(tri["frame"]) if i % every == 0}
    out = []
    for f, image in read_video(base / "media" / "cam0_test.mp4", set(keep)):
        i = keep[f]
        slot = int(np.argmax(labels["found"][f]))
        s = _sample(image, labels["uv"][f, slot], handedness="right", xyz=tri["xyz_cam0"][i], K=tri["K0"],
                    name=f"cam0_test:{f}")
        s["dist"] = tri["dist0"].astype(np.float32)
        out.append(s)
    return out


# ------------------------------------------------------------------ crops
def crop_box(uv, scale=1.3):
    """Square (cx, cy, side) around the keypoints' box x scale (the detector's crop)."""
    lo, hi = uv.min(0), uv.max(0)
    return (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, float(max(hi - lo).max() * scale)


def crop_affine(cx, cy, side, out=128, angle_deg=0.0, mirror=False):
    """2x3 affine from image px to crop px (pixel centres at integers): the square of `side`
    centred on (cx, cy), rotated by angle (counter-clockwise in the crop), optionally mirrored."""
    s = out / side
    a = np.deg2rad(angle_deg)
    R = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) * s
    if mirror:
        R = np.diag([-1.0, 1.0]) @ R
    c = (out - 1) / 2.0
    t = np.array([c, c]) - R @ np.array([cx, cy])
    return np.hstack([R, t[:, None]])


def warp(image, M, out=128, replicate=False):
    """Apply a crop_affine (bilinear). Outside the image: reflected, or with replicate=True
    the edge pixels repeated, as the detector's crops (detector.CropTransform.cut) repeat them."""
    import cv2
    border = cv2.BORDER_REPLICATE if replicate else cv2.BORDER_REFLECT_101
    return cv2.warpAffine(image, M, (out, out), flags=cv2.INTER_LINEAR, borderMode=border)


def apply_affine(M, uv):
    """(...,2) px -> (...,2) px under a 2x3 affine."""
    return uv @ M[:, :2].T + M[:, 2]
