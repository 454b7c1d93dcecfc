"""The detector on people the project never trained on (`handeval people`).

The held-back people are named in real_data (WILD_HELD_BACK: one clip each of video/wild,
tracked as a video; ELEVEN_K_HELD_BACK: 37 people's 11K Hands photos, each on its own with
the photo settings). Their labels are MediaPipe's (pseudo-labels, not ground truth), so
these figures say how close the pipeline comes to MediaPipe on strangers:

* found: of MediaPipe's hands (one of two overlapping detections of one hand dropped), the
  share that an output hand lies on (its joints' centre within half the hand's size);
* false hands per frame: output hands on none of MediaPipe's hands. MediaPipe misses hands
  (touching, washing, blurred: research/false_hands.py --montage shows them), and a hand it
  missed counts here too; so also `false_sure`: false hands per frame over the frames where
  MediaPipe found two hands, where an output on neither is no hand of the (one) person;
* error: mean joint distance / hand size (the side of the joints' box), over the found
  hands whose label passes real_data.reliable_hands; median and mean, and PCK at 0.1 of the
  hand's size (share of joints);
* side: output handedness against the label (the clips: MediaPipe's, the hand as it
  appears; the photos: the person's hand from HandInfo.csv), and the mean error of the
  hands read as the wrong side against the others'.
"""
from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from handmocap.training import real_data

PCK_AT = 0.1                                   # PCK threshold, share of the hand's size
ON_HAND = 0.5                                  # an output lies on a label within this share of its size
CURVE = np.linspace(0.0, 0.3, 31)              # thresholds of the PCK plot


def frames_of_clip(video, jitter_seed=None):
    """(BGR frame, MediaPipe hands (k,21,2), reliable (k,) bool, sides [k]) per frame of a
    clip: every hand MediaPipe found, one of two overlapping detections dropped.
    jitter_seed: every pixel moved by a seeded -1, 0 or +1 (of 255), an imperceptible change."""
    lab = real_data.load_pseudo_labels(video)
    reliable, twice = real_data.reliable_hands(lab), real_data.found_twice(lab)
    rng = None if jitter_seed is None else np.random.default_rng([jitter_seed, zlib.crc32(Path(video).stem.encode())])
    for f, rgb in real_data.read_video(video):
        if f >= len(lab["found"]):
            break
        if rng is not None:
            rgb = moved_pixels(rgb, rng)
        slots = list(np.flatnonzero(lab["found"][f]))[:1 if twice[f] else 2]
        yield (np.ascontiguousarray(rgb[..., ::-1]), lab["uv"][f, slots], reliable[f, slots],
               ["right" if lab["handedness"][f, s] == 0 else "left" for s in slots])


def moved_pixels(image, rng):
    """uint8 `image` with every value moved by -1, 0 or +1 drawn from `rng` (clipped to 0..255): an
    imperceptible change that a chaotic tracker answers with another run (jitter_rows)."""
    return np.clip(image.astype(np.int16) + rng.integers(-1, 2, image.shape, dtype=np.int16), 0, 255).astype(np.uint8)


def frames_of_photos(samples):
    """The same tuples for real_data samples (one reliable hand each)."""
    for s in samples:
        yield (np.ascontiguousarray(s["image"][..., ::-1]), s["uv"][None], np.ones(1, bool), [s["handedness"]])


def nearest_label(uv, labels):
    """(index of the label hand nearest to an output hand's joints uv (21,2), its distance
    in that label's hand sizes, centre to centre), or (-1, inf) with no labels (k,21,2). The
    output lies on that hand when the distance is below ON_HAND, else it is a false hand."""
    dist = [np.linalg.norm(uv.mean(0) - label.mean(0)) / real_data.hand_size(label) for label in labels]
    return (int(np.argmin(dist)), float(min(dist))) if dist else (-1, np.inf)


def clip_fps(video):
    """The frame rate a clip's pseudo-labels give (30 where it is no rate: a variable-rate
    webm's container says 1000)."""
    fps = float(real_data.load_pseudo_labels(video)["fps"])
    return fps if 1.0 <= fps <= 240.0 else 30.0


def scored_hands(detector, video):
    """A clip tracked by `detector` (reset first), frame by frame as score_outputs scores it:
    (frame BGR, [(output hand, its reliable MediaPipe label (21,2) float64, the crop its track
    read it on, None for a track new on this frame, MediaPipe's side "right" / "left")]), for the
    studies that look again at the hands `handeval people` scores (research/tracked_turns.py and
    others)."""
    detector.reset()
    fps = clip_fps(video)
    for f, (image, hands, reliable, sides) in enumerate(frames_of_clip(video)):
        read_on = {t.track_id: t.crop for t in detector.tracks}     # the crops this frame is read on
        scored = []
        for h in detector.process(image, f / fps):
            k, dist = nearest_label(h["uv"], hands)
            if dist < ON_HAND and reliable[k]:
                scored.append((h, hands[k].astype(np.float64), read_on.get(h["track_id"]), sides[k]))
        yield image, scored


def shake(track):
    """|uv(t) - 2 uv(t-1) + uv(t-2)| of a hand's last three (21,2) joints, median over the
    joints, / its size: how much the joints jump about from frame to frame (a hand moving
    steadily scores 0)."""
    a, b, c = track[-3:]
    return float(np.median(np.linalg.norm(c - 2 * b + a, axis=-1)) / real_data.hand_size(c))


def label_shakes(previous, hands):
    """The shake of MediaPipe's hands of this frame (k,21,2) that continue a hand of each of
    the two frames before (`previous`: their labels, oldest first; nearest centre within
    ON_HAND of its size): the same measure on the reference."""
    out = []
    for uv in hands:
        chain = [uv]
        for before in previous[::-1]:
            k, dist = nearest_label(chain[-1], before)
            if dist >= ON_HAND:
                break
            chain.append(before[k])
        if len(chain) == 3:
            out.append(shake(chain[::-1]))
    return out


def score_frames(detector, frames, stills=False, fps=30.0):
    """Run `detector` over `frames` (frames_of_*; a clip at `fps`; stills: each frame on its
    own) and score its hands: score_outputs."""
    def outputs():
        detector.reset()
        for f, (image, hands, reliable, sides) in enumerate(frames):
            if stills:
                detector.reset()
            yield detector.process(image, f / fps), hands, reliable, sides
    return score_outputs(outputs(), stills)


def score_outputs(frames, stills=False):
    """Score a detector's output hands (HandKeypoints hands: track_id, uv, handedness) per
    frame of `frames` ((output hands, MediaPipe hands (k,21,2), reliable (k,), sides [k])):
    a dict of counts and per-hand arrays (err: mean joint error / hand size, joint_err
    (n,21) / hand size, right_side bool, confidence (n,21) and presence (n,): the output
    hand's joint confidences and score, NaN where it has none; shake and label_shake: see
    shake(), ours per track and MediaPipe's; none for stills)."""
    out = {"frames": 0, "labelled": 0, "found": 0, "false": 0, "frames_two": 0, "false_two": 0,
           "err": [], "joint_err": [], "right_side": [],
           "confidence": [], "presence": [], "shake": [], "label_shake": []}
    tracks, previous = {}, []
    for found, hands, reliable, sides in frames:
        out["frames"] += 1
        out["labelled"] += len(hands)
        out["frames_two"] += len(hands) == 2
        hit = set()
        if not stills:
            out["label_shake"] += label_shakes(previous, hands)
            previous = (previous + [hands])[-2:]
            tracks = {h["track_id"]: (tracks.get(h["track_id"], []) + [h["uv"]])[-3:] for h in found}
            out["shake"] += [shake(t) for t in tracks.values() if len(t) == 3]
        for h in found:
            k, dist = nearest_label(h["uv"], hands)
            if dist >= ON_HAND:
                out["false"] += 1
                out["false_two"] += len(hands) == 2
                continue
            hit.add(k)
            if reliable[k]:
                size = real_data.hand_size(hands[k])
                joint = np.linalg.norm(h["uv"] - hands[k], axis=-1) / size
                out["err"].append(joint.mean())
                out["joint_err"].append(joint)
                out["right_side"].append(h["handedness"] == sides[k])
                out["confidence"].append(h.get("confidence", np.full(21, np.nan)))
                out["presence"].append(h.get("score", np.nan))
        out["found"] += len(hit)
    for k in ("err", "right_side", "presence", "shake", "label_shake"):
        out[k] = np.asarray(out[k])
    for k in ("joint_err", "confidence"):
        out[k] = np.asarray(out[k], dtype=float).reshape(-1, 21)
    return out


def summary(s):
    """Figures of one score_frames result (or of several merged)."""
    err, right = s["err"], s["right_side"].astype(bool)
    n = len(err)
    return {"frames": s["frames"], "labelled": s["labelled"], "found": s["found"] / max(s["labelled"], 1),
            "false_per_frame": s["false"] / max(s["frames"], 1), "scored": n,
            "false_sure": s.get("false_two", 0) / s["frames_two"] if s.get("frames_two") else np.nan,
            "median_err": float(np.median(err)) if n else np.nan, "mean_err": float(err.mean()) if n else np.nan,
            "pck": float((s["joint_err"] <= PCK_AT).mean()) if n else np.nan,
            "side": float(right.mean()) if n else np.nan,
            "wrong_side_ratio": float(err[~right].mean() / err[right].mean()) if (~right).any() and right.any()
            else np.nan,
            "curve": [float((s["joint_err"] <= t).mean()) if n else 0.0 for t in CURVE],
            "shake": float(np.median(s["shake"])) if len(s.get("shake", ())) else np.nan,
            "mediapipe_shake": float(np.median(s["label_shake"])) if len(s.get("label_shake", ())) else np.nan}


def merge(results):
    """One score_frames-like dict of several."""
    return {"frames": sum(r["frames"] for r in results), "labelled": sum(r["labelled"] for r in results),
            "found": sum(r["found"] for r in results), "false": sum(r["false"] for r in results),
            **{k: sum(r.get(k, 0) for r in results) for k in ("frames_two", "false_two")},
            **{k: np.concatenate([r[k] for r in results])
               for k in ("err", "joint_err", "right_side", "confidence", "presence")},
            **{k: np.concatenate([r.get(k, np.zeros(0)) for r in results]) for k in ("shake", "label_shake")}}


def row(name, m):
    f = lambda x, spec=".3f": "–" if not np.isfinite(x) else format(x, spec)  # noqa: E731
    return (f"| {name} | {m['frames']} | {m['labelled']} | {100 * m['found']:.1f} | {m['false_per_frame']:.3f} | "
            f"{f(m['median_err'])} | {f(m['mean_err'])} | {f(m['pck'])} | {f(100 * m['side'], '.1f')} | "
            f"{f(m['wrong_side_ratio'], '.2f')} | {f(m['shake'], '.4f')} ({f(m['mediapipe_shake'], '.4f')}) |")


HEAD = ("| held-back set | frames | MediaPipe's hands | found % | false hands / frame | error / hand size, median | "
        "mean | PCK@0.1 | side right % | wrong-side error ratio | shake (MediaPipe's) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|")


JITTER_KEYS = (("found", "found %", 100), ("false_per_frame", "false hands / frame", 1),
               ("false_sure", "false / frame where MediaPipe found two", 1), ("median_err", "median", 1),
               ("mean_err", "mean", 1), ("pck", "PCK@0.1", 1), ("side", "side right %", 100),
               ("wrong_side_ratio", "wrong-side error ratio", 1), ("shake", "shake", 1))


def jitter_rows(runs):
    """The clips' figures as they are (`runs[0]`, a summary) and over n more runs with the
    frames moved by -1/0/+1 (seeds 0..n-1): a tracker is chaotic (a track born or ended a
    frame earlier changes every frame after it), so two versions of the code whose figures
    differ by less than this spread are not told apart by these clips. -> markdown rows."""
    out = ["", "| clips, frames moved by -1/0/+1 | " + " | ".join(name for _, name, _ in JITTER_KEYS) + " |",
           "|---|" + "---|" * len(JITTER_KEYS)]
    for i, m in enumerate(runs):
        out.append(f"| {'as they are' if i == 0 else f'seed {i - 1}'} | "
                   + " | ".join(f"{scale * m.get(k, np.nan):.3f}" for k, _, scale in JITTER_KEYS) + " |")
    for name, fn in (("mean", np.mean), ("spread (max - min)", np.ptp)):
        out.append(f"| **{name}** | " + " | ".join(f"{scale * fn([m.get(k, np.nan) for m in runs]):.3f}"
                                                  for k, _, scale in JITTER_KEYS) + " |")
    return out


CLIPS = "wild clips (9 people, tracked)"
WILD3_CLIPS = "wild3 clips (4 people, tracked)"
TRAINING_CLIPS = "training people's clips (tracked; the finder trained on them, DetNet on video/wild's)"


def run(shared, models=None, per_clip=True, jitter=0, log=print, training=False):
    """Score the detector (HandDetector.load keywords `models`: detnet, finder, side_detnet and
    settings) on every held-back person; -> (markdown table, {set: summary}). The clips of
    video/wild (CLIPS, comparable with earlier sessions' figures) and of video/wild3
    (WILD3_CLIPS: pianos from above, hand washing, signers; where the pack has them) are
    summed apart. jitter: video/wild's clips again this many times with their frames moved by
    -1/0/+1 (jitter_rows). training=True: the training people's clips of both drops instead
    (no photos), to choose detector settings on without reading the held-back people; DetNet
    and the finder trained on their frames, so these figures are never accuracy."""
    from handmocap.perception.detector import PHOTO_SETTINGS, HandDetector
    models = dict(models or {})
    video_det = HandDetector.load(**models)
    rows, results, every_clip, videos_of = [HEAD], {}, [], {}
    groups = ({TRAINING_CLIPS: real_data.WILD_DROPS} if training
              else {CLIPS: ("wild",), WILD3_CLIPS: ("wild3",)})
    for name, drops in groups.items():
        clips, videos_of[name] = [], real_data.wild_clips(shared, held_back=not training, drops=drops)
        for video in videos_of[name]:
            clips.append(score_frames(video_det, frames_of_clip(video), fps=clip_fps(video)))
            scene = real_data.HELD_BACK_SCENES.get(video.stem)
            if per_clip:
                rows.append(row(f"{video.stem} ({scene})" if scene else video.stem, summary(clips[-1])))
            log(f"  {video.stem}: {summary(clips[-1])['found']:.1%} found")
        if clips:
            results[name] = summary(merge(clips))
            every_clip += clips
    if not training:
        photo_det = HandDetector.load(**{**PHOTO_SETTINGS, **models})
        photos = score_frames(photo_det, frames_of_photos(real_data.load_11khands(shared, held_back=True)),
                              stills=True)
        results["11K Hands photos (37 people, stills)"] = summary(photos)
        results["all held-back people"] = summary(merge(every_clip + [photos]))
    name = TRAINING_CLIPS if training else CLIPS
    videos = videos_of[name]
    rows += [row(f"**{k}**", v) for k, v in results.items()]
    if jitter:
        runs = [results[name]]
        for seed in range(jitter):
            runs.append(summary(merge([score_frames(video_det, frames_of_clip(v, seed), fps=clip_fps(v))
                                       for v in videos])))
            log(f"  clips, frames moved (seed {seed}): {runs[-1]['found']:.1%} found")
        rows += jitter_rows(runs)
        results["clips, frames moved"] = {k: [m[k] for m in runs] for k, _, _ in JITTER_KEYS}
    return "\n".join(rows), results
