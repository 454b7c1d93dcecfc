"""A DetNet training job's data, packed small enough to travel to a lent GPU machine.

    handtrain detnet --write-pack runs/device/pack [--pack-mb 24]      (here, beside the data)
    handtrain detnet --pack runs/device/pack --device cuda --amp --workers 14 --minutes 7 ...

A lent machine reaches nothing outside it and gets the checkout and at most 64 MiB of
carried files; `../shared` does not travel. So the job's data goes as one folder:

* real.npz: real context crops (detnet_data.CTX px, JPEG) of the training people, with
  their labels as in the real cache (uv, right, weight, source, xyz, has_3d), the
  held-back people's crops for the run's own validation log (`held`; never trained on:
  BatchMaker draws from ~held alone), and no-hand crops;
* synth.npz: rendered 128 px crops (JPEG) with their 2D and 3D labels, and a held-out
  synthetic set for validation;
* in real.npz too, every 2nd crop of an arm without its hand (detnet_data.build_arm_cache;
  `arm`, for --arm-neg), where that cache was given;
* for `--backbone lite0` (or lite2: `imagenet_in_pack`), the trunk's ImageNet weights in float16 (IMAGENET_IN_PACK, 6 MB):
  the machine has no registry to install the package that ships them.

Which crops go: the byte budget (`--mb`) is split between real and synthetic crops
(`--real-share`); every 11K Hands photo of a training person goes (each is another person),
then every 2nd, 3rd ... frame of the clips and scenes, evenly over the sources, until the
real budget is spent. JPEG at quality 85 costs about 5 kB a 176 px crop. This module is the
format only; train_detnet reads the caches and calls pack().
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from handmocap.perception.crops import CROP

PACK_DIR = Path("runs/device/pack")
HAND_KEYS = ("uv", "right", "weight", "held", "source", "xyz", "has_3d")
SYNTH_KEYS = ("uv", "xyz_rel", "xyz", "handedness", "in_image")
HARD_KINDS = ("arm", "near", "face")    # hard negatives a pack can carry (train_detnet --arm-neg, --near-neg, --face-neg)
LABEL_BYTES = 250           # a crop's labels (float16 uv and xyz) in the compressed .npz, about


def imagenet_in_pack(backbone: str) -> str:
    """The file in a pack that carries `backbone`'s trunk's ImageNet weights, float16 (a run from
    ImageNet weights on a lent machine, which has no registry)."""
    return f"imagenet_{backbone}.pt"


IMAGENET_IN_PACK = imagenet_in_pack("lite0")


def jpeg_blobs(images, quality=85):
    """(n,H,W,3) uint8 -> n JPEG files, each a (bytes,) uint8 array."""
    return [cv2.imencode(".jpg", np.ascontiguousarray(im), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])[1]
            for im in images]


def joined(blobs):
    """JPEG files -> (bytes (m,) uint8, offsets (n+1,) int64): end to end."""
    offsets = np.concatenate([[0], np.cumsum([len(b) for b in blobs])]).astype(np.int64)
    return (np.concatenate(blobs) if blobs else np.zeros(0, np.uint8)), offsets


def encode_jpegs(images, quality=85):
    """(n,H,W,3) uint8 -> (bytes (m,) uint8, offsets (n+1,) int64): the JPEGs end to end."""
    return joined(jpeg_blobs(images, quality))


def decode_jpegs(data, offsets):
    """Inverse of encode_jpegs: (n,H,W,3) uint8 (the channel order they were encoded in)."""
    if len(offsets) < 2:
        return np.zeros((0, CROP, CROP, 3), np.uint8)
    return np.stack([cv2.imdecode(data[offsets[i]:offsets[i + 1]], cv2.IMREAD_COLOR) for i in range(len(offsets) - 1)])


def pick_real(real, budget_bytes, crop_bytes):
    """Indices of the real cache's hands to pack, within budget_bytes given each crop's
    bytes (crop_bytes (n,)): every held-back crop of a person (for validation, at most 400),
    every training 11K Hands photo, then the other training crops thinned evenly per source
    (the largest share of each that fits, evenly spaced in time)."""
    source = real["source"].astype(str)
    held = np.flatnonzero(real["held"] & np.char.startswith(source, "heldback/"))
    held = held[np.linspace(0, len(held) - 1, min(400, len(held))).astype(int)] if len(held) else held
    train = np.flatnonzero(~real["held"])
    photos = train[np.char.find(source[train], "11k") >= 0]
    rest = np.setdiff1d(train, photos)
    groups = [rest[source[rest] == s] for s in np.unique(source[rest])]

    def thinned(share):
        return [g[np.unique(np.linspace(0, len(g) - 1, int(round(share * len(g)))).astype(int))] for g in groups]
    room = budget_bytes - crop_bytes[held].sum() - crop_bytes[photos].sum()
    lo, hi = 0.0, 1.0
    for _ in range(20):                 # the largest share that fits (bisection)
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if sum(crop_bytes[g].sum() for g in thinned(mid)) <= room else (lo, mid)
    return np.sort(np.concatenate([held, photos, *thinned(lo)]))


def pack(out_dir, real, synth, val, mb=24.0, real_share=0.75, quality=85, hard=None, log=print):
    """Write out_dir/real.npz and synth.npz within about `mb` megabytes together, from the
    real cache (detnet_data.load_real), the synthetic crops, the held-out synthetic set
    (detnet_data.load_synth) and optionally hard negatives {kind: cache} (HARD_KINDS:
    detnet_data.load_arms, load_near, load_faces; every 2nd training crop of each goes);
    -> the pack's size, bytes."""
    budget = mb * 1e6
    log(f"encoding {len(real['image'])} real crops once to know their sizes")
    blobs = jpeg_blobs(real["image"], quality)                  # each crop encoded once: sized, then written
    crop_bytes = np.array([len(b) for b in blobs]) + LABEL_BYTES
    idx = pick_real(real, real_share * budget, crop_bytes)
    neg = np.flatnonzero(~real["neg_held"])[::3]
    negs = {"neg": real["neg"][neg], "neg_arm": real["neg_arm"][neg]}
    for kind, cache in (hard or {}).items():
        negs[kind] = cache[kind][np.flatnonzero(~cache[f"{kind}_held"])[::2]]
    per_synth = _jpeg_bytes(synth["image"], quality) + LABEL_BYTES
    room = budget - crop_bytes[idx].sum() - len(val["image"]) * per_synth - sum(
        len(negs[k]) * _jpeg_bytes(negs[k], quality) for k in ("neg", *HARD_KINDS) if len(negs.get(k, ())))
    n = int(np.clip(room / per_synth, 0, len(synth["image"])))
    pick = np.sort(np.random.default_rng(1).choice(len(synth["image"]), n, replace=False))
    hands = {**{k: real[k][idx] for k in HAND_KEYS}, "jpeg": [blobs[i] for i in idx]}
    size = write_pack(out_dir, hands, negs, {k: v[pick] for k, v in synth.items()}, val, quality)
    log(f"real: {int((~hands['held']).sum())} training crops of {int((~real['held']).sum())}, "
        f"{int(hands['held'].sum())} held-back for validation, {len(neg)} no-hand crops, "
        + "".join(f"{len(negs[k])} {k} crops, " for k in HARD_KINDS if k in negs) + f"synthetic: {n} of "
        f"{len(synth['image'])}, {len(val['image'])} held out; wrote {out_dir}: {size / 1e6:.1f} MB")
    return size


def _jpeg_bytes(images, quality, n=256):
    """Mean JPEG size of n of `images` (evenly spaced), bytes."""
    pick = np.linspace(0, len(images) - 1, min(n, len(images))).astype(int)
    return encode_jpegs(images[pick], quality)[1][-1] / len(pick)


def write_pack(out_dir, hands, negs, synth, val, quality=85):
    """Write the pack: hands {image (n,CTX,CTX,3) or jpeg (n JPEG files, jpeg_blobs), HAND_KEYS},
    negs {neg (m,128,128,3), neg_arm, optionally each of HARD_KINDS (e,128,128,3)},
    synth and val {image (k,128,128,3), SYNTH_KEYS} (load_synth's arrays); -> bytes written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    arrays = {k: hands[k] for k in HAND_KEYS}
    arrays["uv"], arrays["xyz"] = hands["uv"].astype(np.float16), hands["xyz"].astype(np.float16)
    arrays["image_jpeg"], arrays["image_offsets"] = \
        joined(hands["jpeg"]) if "jpeg" in hands else encode_jpegs(hands["image"], quality)
    arrays["neg_jpeg"], arrays["neg_offsets"] = encode_jpegs(negs["neg"], quality)
    arrays["neg_arm"] = negs["neg_arm"]
    for kind in HARD_KINDS:
        if kind in negs:
            arrays[f"{kind}_jpeg"], arrays[f"{kind}_offsets"] = encode_jpegs(negs[kind], quality)
    np.savez_compressed(out_dir / "real.npz", **arrays)
    arrays = {}
    for prefix, s in (("", synth), ("val_", val)):
        arrays[f"{prefix}image_jpeg"], arrays[f"{prefix}image_offsets"] = encode_jpegs(s["image"], quality)
        for k in SYNTH_KEYS:
            arrays[prefix + k] = s[k].astype(np.float16) if s[k].dtype.kind == "f" else s[k]
    np.savez_compressed(out_dir / "synth.npz", **arrays)
    return sum((out_dir / f).stat().st_size for f in ("real.npz", "synth.npz"))


def load_pack(pack_dir):
    """-> (real, synth, synth_val): the dicts train_detnet's BatchMaker and validation take
    (real[kind]: the hard negatives of each of HARD_KINDS the pack has)."""
    pack_dir = Path(pack_dir)
    for f in ("real.npz", "synth.npz"):
        if not (pack_dir / f).is_file():
            raise SystemExit(f"--pack {pack_dir}: no {f} there (make one beside the data pack with "
                             f"`handtrain detnet --write-pack {pack_dir}`)")
    with np.load(pack_dir / "real.npz") as z:
        real = {k: z[k] for k in HAND_KEYS + ("neg_arm",)}
        real["image"] = decode_jpegs(z["image_jpeg"], z["image_offsets"])
        real["neg"] = decode_jpegs(z["neg_jpeg"], z["neg_offsets"])
        for kind in HARD_KINDS:
            if f"{kind}_jpeg" in z.files:
                real[kind] = decode_jpegs(z[f"{kind}_jpeg"], z[f"{kind}_offsets"])
    real["neg_held"] = np.zeros(len(real["neg"]), bool)     # only training negatives travel
    real["uv"], real["xyz"] = real["uv"].astype(np.float32), real["xyz"].astype(np.float32)
    with np.load(pack_dir / "synth.npz") as z:
        synth, val = ({k: z[prefix + k] for k in SYNTH_KEYS} for prefix in ("", "val_"))
        synth["image"] = decode_jpegs(z["image_jpeg"], z["image_offsets"])
        val["image"] = decode_jpegs(z["val_image_jpeg"], z["val_image_offsets"])
    for s in (synth, val):
        for k in ("uv", "xyz_rel", "xyz"):
            s[k] = s[k].astype(np.float32)
    return real, synth, val
