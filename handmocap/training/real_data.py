"""Loaders for the real hand data pack (shared/data/README.md), all in MP joint order.

Every loader returns a list of samples, each a dict:
    image (H,W,3) uint8 RGB · uv (21,2) float32 px · visible (21,) bool ·
    handedness "left" / "right" / None (the hand as it appears in the image) ·
    xyz (21,3) float32 metres camera frame and K (3,3) where the set has them · name str.
Video pseudo-labels (MediaPipe, not ground truth) come as per-frame arrays instead
(`load_pseudo_labels`, `read_video`), since whole clips do not fit in memory as samples.

Splits (README "Use" lines): training may use howiema subject 001, the MediaPipe
pseudo-labels of TRAIN_VIDEOS, the clips of video/wild and video/wild3 but WILD_HELD_BACK
and WILD3_HELD_BACK, the 11K Hands people but ELEVEN_K_HELD_BACK, and images/scenes (one
person). Evaluation only: howiema 040, temugeb_stereo, cmu_hand_labels_sample,
samples/mmpose/*, images/photos, and the held-back people (WILD_HELD_BACK, WILD3_HELD_BACK,
ELEVEN_K_HELD_BACK): the people the project is judged on are people it never trained on, so
its own figures come from people held back by name.
"""
import json
from pathlib import Path

import numpy as np

from handmocap.training.pose_data import SHARED_DATA
from handmocap.perception.crops import CROP

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

# People held back from every training run (validation by person). video/wild: one clip a
# person (the pack's README names the clips of one repository that show different people),
# chosen to cover its conditions: small hands of waist-up signers (klyct, rodrmilano00),
# two hands touching (ROSA, limpiar, want), a sink seen from above in dim light
# (HandWash_017), a backlit low-angle webcam with motion blur (deepanjanroy), close-ups
# counting fingers (CoderEnko007), a hand at the face (akstheme), brown skin (SHREYASH1504,
# akstheme). 11K Hands: every 5th person id in sorted order (37 of 184 people).
WILD_HELD_BACK = ("klyct__abrazo", "klyct__limpiar", "Kirichovka__want", "SHREYASH1504__v_video",
                  "huiwen99__HandWash_017", "deepanjanroy__hand", "CoderEnko007__hand", "rodrmilano00__ROSA",
                  "akstheme__gesture")
WILD_UNLABELLED = ("aidenpearce001__hand",)      # MediaPipe found no hand in any frame: nothing to learn or score
# video/wild3 (the pack's third drop; its README names who is in which clip), one or two
# clips a person: the second pianist, seen from above at a slant (hmj6589; the other pianist,
# jackier42, trains), hands washing and rubbing in a sink (limchaesung), the ASL signer
# (AlpYksl__YES and __again: fists, hands at the chin) and the German signer with small hands
# pressed together (AlpYksl__bitte)
WILD3_HELD_BACK = ("hmj6589__piano_hands", "limchaesung__hand", "AlpYksl__YES", "AlpYksl__again", "AlpYksl__bitte")
# the video/ folders of the pack's drops of people's own clips: the second (wild) and third (wild3)
WILD_DROPS = ("wild", "wild3")
# what each held-back clip shows (the tables name the scene beside the clip)
HELD_BACK_SCENES = {
    "klyct__abrazo": "signer, waist-up, small hands", "klyct__limpiar": "signer, hands touching",
    "Kirichovka__want": "two hands touching", "SHREYASH1504__v_video": "webcam, brown skin",
    "huiwen99__HandWash_017": "sink from above, dim", "deepanjanroy__hand": "backlit webcam, motion blur",
    "CoderEnko007__hand": "close-up, counting fingers", "rodrmilano00__ROSA": "signer, small hands",
    "akstheme__gesture": "hand at the face", "hmj6589__piano_hands": "piano from above, two hands",
    "limchaesung__hand": "hand washing, rubbing", "AlpYksl__YES": "ASL signer, fist",
    "AlpYksl__again": "ASL signer, two hands", "AlpYksl__bitte": "German signer, small hands pressed"}
ELEVEN_K_HELD_BACK = (
    "0000000", "0000012", "0000027", "0000054", "0000064", "0000084", "0000501", "0000507", "0000528", "0000539",
    "0000559", "0000574", "0000588", "0001003", "0001013", "0001021", "0001028", "0001034", "0001041", "0001051",
    "0001061", "0001073", "0001081", "0001090", "0001506", "0001516", "0001525", "0001532", "0001539", "0001545",
    "0001552", "0001558", "0001566", "0001573", "0001593", "1200000", "6000000")
# Pseudo-label filter (reliable_hands): a hand is kept when its joint box is at least
# MIN_HAND_PX, it is not one of two overlapping detections (IoU > DUPLICATE_IOU: one hand
# found twice) nor one of two hands given the same side, and (videos) a hand of the same
# side lies within MAX_JUMP x its size (mean joint distance) in the frame before or after:
# MediaPipe's misreads flicker, a real hand moves little in 1/30 s.
MIN_HAND_PX, DUPLICATE_IOU, MAX_JUMP = 16.0, 0.3, 0.3

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
    score (F,2), handedness (F,2) int8 0 Right / 1 Left / -1 empty, found (F,2), fps, size.
    For an image folder (images/<folder>) the file beside it, with names (N,) and size (N,2)
    per image instead of fps and size."""
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


def hand_size(uv):
    """(...,21,2) px -> (...) the side of the joints' box (the unit the errors are quoted in)."""
    return (uv.max(-2) - uv.min(-2)).max(-1)


FORESHORTENED = 0.25    # wrist -> middle knuckle under this share of hand_size: the palm at the camera, fingers first


def foreshortened(uv):
    """(...,21,2) px -> (...) bool: hands seen fingers first, where no angle in the image is well
    defined (session 52: 55% of the held-back signer Kirichovka__want's hands, 0.9% of the real
    training crops)."""
    return np.linalg.norm(uv[..., 9, :] - uv[..., 0, :], axis=-1) / hand_size(uv) < FORESHORTENED


def found_twice(lab):
    """(F,) bool: the frames whose two pseudo-labelled hands' joint boxes overlap by more
    than DUPLICATE_IOU (one hand found twice)."""
    from handmocap.perception.hand_finder import box_iou
    twice = np.zeros(len(lab["found"]), bool)
    for f in np.flatnonzero(lab["found"].all(1)):
        boxes = np.concatenate([lab["uv"][f].min(-2), lab["uv"][f].max(-2)], -1)    # (2,4)
        twice[f] = box_iou(boxes[0], boxes[1])[0, 0] > DUPLICATE_IOU
    return twice


def reliable_hands(lab, video=True):
    """(F,2) bool: the pseudo-labelled hands (found) that pass the filter described at
    MIN_HAND_PX / DUPLICATE_IOU / MAX_JUMP; video=False (photos) skips the temporal test."""
    found, uv, side = lab["found"].astype(bool), lab["uv"], lab["handedness"]
    size = hand_size(uv)
    ok = found & (size >= MIN_HAND_PX)
    ok[found_twice(lab) | (found.all(1) & (side[:, 0] == side[:, 1]))] = False
    if not video:
        return ok
    steady = np.zeros_like(ok)
    for f, s in zip(*np.nonzero(ok)):
        for g in (f - 1, f + 1):
            if 0 <= g < len(found):
                for t in np.flatnonzero(found[g] & (side[g] == side[f, s])):
                    if np.linalg.norm(uv[f, s] - uv[g, t], axis=-1).mean() < MAX_JUMP * size[f, s]:
                        steady[f, s] = True
    return ok & steady


def wild_clips(root=SHARED_DATA, held_back=False, drops=("wild",)):
    """The clips with pseudo-labels of the drops' folders (video/wild, and video/wild3 with
    drops=WILD_DROPS; a drop the pack lacks is skipped): those of WILD_HELD_BACK and
    WILD3_HELD_BACK (held_back=True) or the others (training), sorted paths, drop by drop.
    The default, the second drop alone, keeps the figures of earlier sessions comparable."""
    held = set(WILD_HELD_BACK) | set(WILD3_HELD_BACK)
    clips = [p for drop in drops if (Path(root) / "video" / drop).is_dir()
             for p in sorted((Path(root) / "video" / drop).iterdir())
             if p.suffix in (".mp4", ".mov", ".webm") and p.with_suffix(".mediapipe.npz").is_file()
             and p.stem not in WILD_UNLABELLED]
    return [p for p in clips if (p.stem in held) == held_back]


def load_11khands(root=SHARED_DATA, held_back=False):
    """11K Hands photos (about 180x180, one hand each) of the people in ELEVEN_K_HELD_BACK
    (held_back=True) or of the others, as samples: uv = MediaPipe's 2D (pseudo-labels),
    handedness = the person's hand from HandInfo.csv (the photos are not mirrored), name =
    "<id>/<image>". Kept where MediaPipe found one reliable hand (reliable_hands) and its side
    agrees with the table's (95% of them): where it does not, its joints are read for the
    other hand's chirality."""
    import csv
    base = Path(root) / "images"
    info = {r["imageName"]: r for r in csv.DictReader(open(base / "11khands" / "HandInfo.csv"))}
    lab = load_pseudo_labels(base / "11khands")
    ok = reliable_hands(lab, video=False)
    out = []
    for i, name in enumerate(lab["names"]):
        row = info[str(name)]
        if (row["id"] in ELEVEN_K_HELD_BACK) != held_back or not ok[i].any():
            continue
        s = int(np.argmax(ok[i]))
        side = "right" if "right" in row["aspectOfHand"] else "left"
        if ("right" if lab["handedness"][i, s] == 0 else "left") == side:
            out.append(_sample(read_image(base / "11khands" / str(name)), lab["uv"][i, s], handedness=side,
                               name=f"{row['id']}/{name}"))
    return out


def load_scenes(root=SHARED_DATA):
    """images/scenes (one person, many scenes; training only): samples of its reliable
    pseudo-labelled hands, handedness as MediaPipe labels the hand as it appears."""
    base = Path(root) / "images" / "scenes"
    lab = load_pseudo_labels(base)
    ok = reliable_hands(lab, video=False)
    out = []
    for i, name in enumerate(lab["names"]):
        slots = np.flatnonzero(ok[i])
        if len(slots):
            image = read_image(base / str(name))
            out += [_sample(image, lab["uv"][i, s], handedness="right" if lab["handedness"][i, s] == 0 else "left",
                            name=f"scenes/{name}") for s in slots]
    return out


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


def crop_affine(cx, cy, side, out=CROP, angle_deg=0.0, mirror=False):
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


def warp(image, M, out=CROP, replicate=False):
    """Apply a crop_affine (bilinear). Outside the image: reflected, or with replicate=True
    the edge pixels repeated, as the detector's crops (crops.CropTransform.cut) repeat them."""
    import cv2
    border = cv2.BORDER_REPLICATE if replicate else cv2.BORDER_REFLECT_101
    return cv2.warpAffine(image, M, (out, out), flags=cv2.INTER_LINEAR, borderMode=border)


def apply_affine(M, uv):
    """(...,2) px -> (...,2) px under a 2x3 affine."""
    return uv @ M[:, :2].T + M[:, 2]
