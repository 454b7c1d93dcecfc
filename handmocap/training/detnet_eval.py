"""DetNet's validation (never training data): held-out synthetic shards, the held-out tail of
every training video (last 15% of frames, 15 frames gap), howiema 001 sequences L8/R8 (not
used for training) and the held-back people's crops (`people_*`: error / hand size and PCK at
0.1 of it, against MediaPipe's labels).
"""
import numpy as np

from handmocap.perception.tracks import logit
from handmocap.perception.skeleton import ROOT
from handmocap.training import real_data
from handmocap.training.detnet_batches import rotate_mirror_3d
from handmocap.training.detnet_data import CTX, CTX_CROP_SIDE, DROP_CACHES, HARD_NEGATIVES, HELD_BACK_SOURCE, load_synth
from handmocap.perception.crops import CROP


PALM_M = 0.093               # |wrist - middle MCP| that real held-out 3D errors are quoted at (temugeb's median)

# read-outs measured at each validation; the one best on held-out synthetic crops is exported
# (the first wins a tie, and is the one the real held-out sets are scored with)
READ_OUTS = ("softmax", "logquad", "soft3", "none")


def read_outs(net):
    """The read-outs `net` offers (READ_OUTS, and "fine" first with a fine head)."""
    return (("fine",) if getattr(net, "fine", None) is not None else ()) + READ_OUTS


# ------------------------------------------------------------------ validation
def shown_as_right(image, uv, xyz, left):
    """Copies of crops image (n,S,S,3), their joints uv (n,21,2) crop px and xyz (n,21,3)
    with the hands where left (n,) bool mirrored into right ones, as DetNet is shown them:
    the image flipped left-right, u -> S - 1 - u, x -> -x."""
    image, uv, xyz = image.copy(), uv.copy(), xyz.copy()
    image[left] = image[left][:, :, ::-1]
    uv[left, :, 0] = image.shape[2] - 1 - uv[left, :, 0]
    xyz[left, :, 0] *= -1
    return image, uv, xyz


def synth_val_set(path, limit=512):
    """Held-out synthetic crops as the detector sees them: left hands mirrored to the right
    (image, uv, xyz_rel), plus the unmirrored images for the handedness head. `path`: a
    shard directory, or the arrays load_synth gives (a device pack's)."""
    s = path if isinstance(path, dict) else load_synth([path], limit)
    if s is None:
        return None
    left = s["handedness"] == 1
    image, uv, xyz = shown_as_right(s["image"], s["uv"], s["xyz_rel"], left)
    bone_m = np.linalg.norm(s["xyz"][:, 0] - s["xyz"][:, ROOT], axis=-1)
    return {"image": image, "raw": s["image"], "uv": uv, "xyz": xyz, "in_image": s["in_image"],
            "right": (~left).astype(np.float32), "bone_m": bone_m}


def heldout_groups(source):
    """{group: (N,) bool} of real_val_set's crops by their `source` (N,): howiema 001, the
    training videos' held-out tails, the held-back people's clips and their photos."""
    source = np.asarray(source).astype(str)
    how, people = np.char.startswith(source, "howiema"), np.char.startswith(source, HELD_BACK_SOURCE)
    photos = np.char.startswith(source, HELD_BACK_SOURCE + "11k/")
    later = later_drops(source)
    return {"howiema 001": how, "training videos' tails": ~how & ~people,
            "held-back clips": people & ~photos & ~later, "held-back clips, third drop": later,
            "held-back photos": photos}


def later_drops(source):
    """(N,) bool: the held-back crops of the later drops' clips (DROP_CACHES), kept out of the
    held-back clips' figures so those stay comparable with the sessions before them."""
    source = np.asarray(source).astype(str)
    return np.any([np.char.startswith(source, f"{HELD_BACK_SOURCE}{drop}/") for drop in DROP_CACHES], axis=0)


def real_val_set(real):
    """Held-out real crops at the detector's crop (box x 1.3, no jitter), shown as right
    hands: every howiema L8/R8 frame, every held-back person's hand in the cache and every
    3rd hand of the training videos' held-out tails."""
    if real is None:
        return None
    idx = np.flatnonzero(real["held"])
    how = np.char.startswith(real["source"][idx].astype(str), "howiema")
    people = np.char.startswith(real["source"][idx].astype(str), HELD_BACK_SOURCE)
    idx = np.concatenate([idx[how], idx[people], idx[~how & ~people][::3]])
    side = CTX_CROP_SIDE
    c = (CTX - 1) / 2
    images, uv = [], []
    for i in idx:
        M = real_data.crop_affine(c, c, side, CROP, 0.0, not real["right"][i])
        images.append(real_data.warp(real["image"][i], M))
        uv.append(real_data.apply_affine(M, real["uv"][i]))
    out = {"image": np.asarray(images), "uv": np.asarray(uv, np.float32), "source": real["source"][idx],
           "neg": real["neg"][real["neg_held"]]}
    if "has_3d" in real:      # MediaPipe's world landmarks, mirrored as the crop is
        out["xyz"] = rotate_mirror_3d(real["xyz"][idx], np.zeros(len(idx)), ~real["right"][idx].astype(bool))
        out["has_3d"] = real["has_3d"][idx]
    return out


def predict(net, images, refines=("softmax",), batch=128):
    """Torch DetNet (eval) on uint8 crops (N,128,128,3), one pass -> {refine: (uv, xyz, conf)},
    presence (N,), right (N,) probabilities (numpy). `net` may also be an exported file
    (quantize_detnet.OnnxNet): its one read-out then stands for every refine asked."""
    if hasattr(net, "predict"):
        read, pres, right = net.predict(images, batch)
        return {r: read for r in refines}, pres, right
    import torch

    from handmocap.training.detnet import read_out
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    reads, pres, right = {r: [] for r in refines}, [], []
    with torch.no_grad():
        for i in range(0, len(images), batch):
            x = torch.from_numpy(np.ascontiguousarray(images[i:i + batch])).to(device).permute(0, 3, 1, 2).float() / 255.0
            out = {k: v.float() for k, v in net(x.contiguous(memory_format=torch.channels_last)).items()}
            for r in refines:
                reads[r].append([t.cpu().numpy() for t in read_out(out["heatmap"], out["location"], net.stride, r,
                                                                               out["heat_logits"], out.get("fine_logits"))])
            pres.append(torch.sigmoid(out["presence"]).cpu().numpy())
            right.append(torch.sigmoid(out["handedness"]).cpu().numpy())
    net.train(was_training)
    return ({r: [np.concatenate(k) for k in zip(*v)] for r, v in reads.items()},
            np.concatenate(pres), np.concatenate(right))


def pck_auc(err_mm, lo=20.0, hi=50.0, steps=15):
    """Paper's 3D PCK over thresholds linspace(20,50) mm -> AUC (trapezoid, normalised)."""
    th = np.linspace(lo, hi, steps)
    pck = (err_mm.reshape(-1)[:, None] <= th).mean(0)
    return float(np.trapezoid(pck, th) / (hi - lo))


def validate(net, sval, rval, refines=("softmax",)):
    """Held-out metrics; syn_px_<refine> for each read-out (2D px over in-crop joints)."""
    m = {}
    if sval is not None:
        reads, pres, _ = predict(net, sval["image"], refines)
        for refine, (uv, xyz, _) in reads.items():
            err2d = np.linalg.norm(uv - sval["uv"], axis=-1)[sval["in_image"]]
            m[f"syn_px_{refine}"] = float(err2d.mean())
            m[f"syn_pck5px_{refine}"] = float((err2d <= 5).mean())
        err3d = np.linalg.norm(xyz - sval["xyz"], axis=-1)
        m["syn_3d_norm"] = float(err3d.mean())
        err_mm = err3d * sval["bone_m"][:, None] * 1000
        m["syn_3d_mm"] = float(err_mm.mean())
        m["syn_3d_auc_20_50mm"] = pck_auc(err_mm)
        m["syn_presence"] = float((pres > 0.5).mean())
        right = predict(net, sval["raw"], ())[2]
        m["syn_handedness_acc"] = float(((right > 0.5) == (sval["right"] > 0.5)).mean())
    if rval is not None:
        reads, pres, right = predict(net, rval["image"], refines[:1])
        err = np.linalg.norm(reads[refines[0]][0] - rval["uv"], axis=-1).mean(-1)
        groups = heldout_groups(rval["source"])
        how, tails, clips, later, photos = (groups[k] for k in ("howiema 001", "training videos' tails", "held-back clips",
                                                                "held-back clips, third drop", "held-back photos"))
        people = clips | later | photos
        if how.any():
            m["howiema001_heldout_px"] = float(err[how].mean())
        if tails.any():
            m["video_heldout_px_vs_mediapipe"] = float(err[tails].mean())
        for name, mask in (("wild", clips), ("wild3", later), ("11k", photos)):
            if mask.any():      # people never trained on, against MediaPipe: error / hand size, PCK at 0.1 of it
                size = real_data.hand_size(rval["uv"][mask])
                joint_err = np.linalg.norm(reads[refines[0]][0][mask] - rval["uv"][mask], axis=-1)
                m[f"people_{name}_median_err"] = float(np.median(err[mask] / size))
                m[f"people_{name}_pck10"] = float((joint_err <= 0.1 * size[:, None]).mean())
        # the same crops mirrored the wrong way (a left hand shown as it is): what a wrong
        # handedness call costs the 2D
        flipped, uv_flipped, _ = shown_as_right(rval["image"], rval["uv"], np.zeros((len(err), 21, 3)),
                                                np.ones(len(err), bool))
        reads_wrong, _, right_wrong = predict(net, flipped, refines[:1])
        err_wrong = np.linalg.norm(reads_wrong[refines[0]][0] - uv_flipped, axis=-1).mean(-1)
        if clips.any():     # the side of held-back clips' hands, shown as right (image) and as left (flipped)
            m["people_side_acc"] = float(np.mean([(right[clips] > 0.5).mean(), (right_wrong[clips] < 0.5).mean()]))
            # the detector's mirror vote: the two readings of one hand averaged in logit space (its logit)
            m["people_side_acc_pair"] = float((logit(right[clips]) > logit(right_wrong[clips])).mean())
        if how.any():
            m["howiema001_heldout_px_wrong_side"] = float(err_wrong[how].mean())
        if tails.any():
            m["video_heldout_px_wrong_side"] = float(err_wrong[tails].mean())
        if people.any():
            m["people_px"], m["people_px_wrong_side"] = float(err[people].mean()), float(err_wrong[people].mean())
        if "has_3d" in rval and rval["has_3d"].any():   # agreement with MediaPipe's 3D, not accuracy
            has = rval["has_3d"]
            err_mm = np.linalg.norm(reads[refines[0]][1][has] - rval["xyz"][has], axis=-1) * PALM_M * 1000
            m["video_heldout_3d_mm_vs_mediapipe"] = float(err_mm.mean())
            m["video_heldout_3d_auc_vs_mediapipe"] = pck_auc(err_mm)
        m["real_presence"] = float((pres > 0.5).mean())
        if len(rval["neg"]):
            m["neg_rejected"] = float((predict(net, rval["neg"], ())[1] < 0.5).mean())
        for kind in HARD_NEGATIVES:
            if len(rval.get(kind, ())):
                m[f"{kind}_rejected"] = float((predict(net, rval[kind], ())[1] < 0.5).mean())
    return m
