"""From a whole camera frame to every hand's keypoints (no bus): finder + DetNet + tracking.

Per frame (`HandDetector.process`):
1. The hand finder (hand_finder.HandFinder) runs when there is no track, when a track was
   lost on the previous frame (or dropped as a duplicate), and every `redetect_every`
   frames (`redetect_every_full` while every track slot is held). Each found box goes to
   the track whose joint box it overlaps best (IoU >= MATCH_IOU, one box per track); a box
   no track matched but inside the crop of a track no box matched (IoU >= 0.3 or its centre
   inside it) is that track's too. A track's box
   informs its handedness, and re-seeds the track's crop when it overlaps the track's
   joints less than `reseed_iou` (a track that slid up the forearm: DetNet's presence
   head alone does not catch it); the other boxes start new tracks (stable integer ids,
   never reused). With every slot taken, the finder returns one box more, and a box no
   track covers replaces the track with the lowest running mean heatmap peak when DetNet's
   peak on the box's crop is `evict_margin` higher (a desk object or a forearm that holds a
   slot must not keep a hand out for good).
2. Every track is cropped the way DetNet was trained (handmocap/synth: square, the hand's
   vertex box x 1.3, i.e. about its 21-joint box x CROP_SCALE, 128 px; `CropTransform`
   records the crop <-> frame mapping), turned in quarter turns (`upright_step`) so that the
   hand appears upright, wrist below the middle finger's base, as MediaPipe turns its
   crops: unturned, a hand hanging down read several times worse. Tracks whose smoothed
   handedness is left are flipped horizontally, so DetNet always sees a right hand; its 2D
   is un-flipped and its 3D mirrored back (x -> -x) and turned back: HandKeypoints'
   xyz_rel is the hand as seen, in the camera's axes.
3. One batched DetNet call for all crops; presence below `presence_threshold` or a mean
   heatmap peak below `min_confidence` ends the track, and so do joints centred outside
   the frame with fewer than `edge_joints` of them inside it, or spread over more than twice
   its size; a new track's crop is refined once
   from its own first 2D prediction (first turned the quarter turn on which DetNet's
   heatmap peaks are highest, and flipped the other way if DetNet's handedness
   outweighs the finder's), and the track is only born if its mean heatmap peak there
   reaches `birth_confidence`: DetNet's presence head is sure of almost anything the
   finder proposes (a mouse on a desk, a face), its heatmap peaks are not. After a hand
   was refused, the finder looks again `unborn_retry` frames later. With
   `test_time_crops` (photos) a new track's reading, with `tracked_test_time_crops` every
   tracked hand's on every frame, is the median over its crop and that many variants of it;
   a tracked hand whose joints' box changed size by more than `second_look` (10%) since the
   last frame gets that second look on `second_look_crops` (2) variants.
4. The next frame's crop of a track comes from this frame's 2D joints (their box, centre
   moved on by half the last displacement, side changing by at most 1.33x per frame), as
   MediaPipe and the paper's videos do.
5. Handedness per track: a running mean in logit space of DetNet's handedness head
   (mapped back through the flip), at detection the finder's, and every
   `mirror_vote_every` frames (and on a new track's crops) the head's answer on the crop
   flipped the other way: a head biased towards one side on an unfamiliar view leans the
   same way on both, and the mean of the two readings cancels the bias. Two tracks that DetNet
   believes are hands (running mean heatmap peak >= `opposite_hands`) and that read as the
   same hand are one person's left and right: the one with the weaker evidence turns. With
   `handedness` "left" or "right" (one known hand) every track is that side, and none of
   this runs.
6. Two tracks on one hand (joint-box IoU >= 0.5, or the smaller box 70% inside the other):
   the lower-scoring one is dropped.
7. The 2D joints published (`uv`) go through a One Euro filter per track (`smooth_min_cutoff`,
   `smooth_beta`; one_euro.py), on the time `process` is given: a still hand's joints shake
   about half as much, and a moving hand's follow it. The track itself follows the
   unfiltered heatmap peaks, and a re-seeded track's filter starts again.

>>> det = HandDetector.load()
>>> hands = det.process(frame_bgr, t)   # HandKeypoints hands (track_id, handedness, score,
...                                      # bbox, uv (21,2) frame px, confidence, xyz_rel)
"""
from __future__ import annotations

import math
import dataclasses
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np

from handmocap.perception.crops import (CROP, CROP_SCALE, HAND_ANGLES, PALM_ANGLE_JOINTS, TEST_TIME_VARIANTS,
                                        CropTransform, angle_apart, box_overlap_of_smaller, crop_for_box,
                                        crop_for_joints, crop_to_frame_xyz, frame_to_crop_xyz, head_angle_in_frame,
                                        nearby_crops, rounded_turn, square_box)
from handmocap.perception.detnet_runner import DETNET_GREY, DetNetRunner
from handmocap.perception.onnx_models import cores, keep_on_helper_cpu, off_helper_cpu
from handmocap.perception.one_euro import OneEuroFilter
from handmocap.perception.hand_finder import GREY_PATH, HandFinder, box_iou, is_grey, sigmoid
from handmocap.perception.rotations import mirror_points
from handmocap.perception.skeleton import normalize_joints
from handmocap.perception.tracks import HANDEDNESS_MEMORY, Track, logit

CENTRE = "centre"           # the fallback that tries the centre square of the frame
MATCH_IOU = 0.3             # a found box is a track's own hand from this overlap with its joint box on
# HandDetector.load's keywords for unrelated photos (reset before each): one chance per hand,
# so no birth threshold; a close-up the finder misses is tried on the centre square; each
# hand read on its crop and 4 variants of it (chosen on training-side stills, docs/models_history.md)
PHOTO_SETTINGS = {"birth_confidence": 0.0, "fallback": CENTRE, "test_time_crops": 4, "smooth_min_cutoff": None}
# HandDetector.load's keywords for video where accuracy is worth ~2.3x the time (offline
# processing, a fast CPU): every tracked hand read on its crop and 4 variants on every frame
# (chosen on training-side clips at three turns, docs/models_history.md; 20 ms a frame against 9
# on the AVX2 machine, MediaPipe 32)
ACCURATE_VIDEO_SETTINGS = {"tracked_test_time_crops": 4}


def _variant_count(name, value):
    """A count of TEST_TIME_VARIANTS (None: 0); a ValueError naming `name` outside 0..6."""
    value = value or 0
    if not 0 <= value <= len(TEST_TIME_VARIANTS):
        raise ValueError(f"{name} must be 0..{len(TEST_TIME_VARIANTS)}, got {value}")
    return value


@dataclass(frozen=True)
class DetectorSettings:
    """Every setting of a HandDetector, with its default and, beside it, what it does: the one
    place the detector node's params (and which of them take null), `handeval --set` and the
    scripts read them from. A HandDetector has each as an attribute of the same name.
    __post_init__ refuses a value out of range (ValueError naming the setting)."""
    max_hands: int = 2                  # hands tracked at most
    # a track is lost below this presence (DetNet's presence head)
    presence_threshold: float = 0.5
    # frames between finder runs while a track slot is free; the finder then also checks the tracks
    redetect_every: int = 10
    # frames between the finder's checks of the tracks (re-seeds, evictions) while every track slot
    # is held (None: redetect_every). Such a run seldom changes anything (the held-back clips: 236
    # runs, 3 re-seeds and 1 eviction in 5,845 frames); 30 took most finder frames off the slowest
    # tenth at 30 fps but did not lower the p95 and CPU of both a one- and a two-hand clip (session 50)
    redetect_every_full: int | None = None
    # the detector's helper threads (DetNet's second thread, the finder beside the crops) kept on one
    # CPU, and the thread reading a frame off it while it does (onnx_models.cpu_split): at 30 fps
    # Linux woke a helper on the busy CPU of the thread that handed it work, and it waited there
    pin_threads: bool = True
    # a periodic finder run (hands tracked, none lost) due on a frame where a track is due a mirror
    # vote or a side reading waits for a frame without one, at most this many frames (0: never
    # waits). 3: no frame pays for both, the slowest 5% of frames 0.6-0.8 ms faster; off since the
    # training people's clips read one piano clip's side 96% -> 39% with it (session 44)
    finder_waits: int = 0
    crop_scale: float = CROP_SCALE      # crop side / the hand's 21-joint box side
    # the finder's score a box needs to be proposed; lower it for a dim or distant camera
    finder_threshold: float = 0.3
    # while hands are tracked, the finder's periodic run goes on a thread of its own (another core:
    # onnxruntime and OpenCV let go of the GIL) while DetNet reads the tracked hands' crops of the
    # same frame; its boxes are then taken as a run in turn's would be (a re-seeded or evicted
    # track is read again), so a finder frame costs about the longer of the two, not their sum.
    # With no track the finder runs on the frame first, as it must; on one core, always in turn
    finder_beside: bool = True
    # a track is lost below this mean heatmap peak too: the presence head stays sure on a crop
    # that slid onto the forearm, the heatmap peaks do drop there (0: off)
    min_confidence: float = 0.1
    # at each periodic run (`redetect_every`, `redetect_every_full`) the finder checks the tracks: a
    # found hand inside a track's crop whose box overlaps the track's joints less than this re-seeds
    # the track from the finder's box (0: never; the finder then only runs while a slot is free)
    reseed_iou: float = 0.3
    # a tracked hand whose joints' box centre lies outside the frame ends its track unless at least
    # this many of its 21 joints lie inside (None: the centre alone decides). A hand entering from
    # the frame's edge (a pianist's from the bottom) has its unseen wrist read far outside, and its
    # centre crossed the edge while DetNet still read it at 0.7. 6 (session 62): the training people's
    # clips found 94.5 -> 95.1%, false 0.085 -> 0.086; the held-back clips as before (10 runs)
    edge_joints: int | None = 6
    # a found hand becomes a track only from this mean heatmap peak on its refined crop on:
    # with min_confidence a hysteresis (chosen on training-side clips by
    # scripts/detector_thresholds.py). DetNet's presence head is sure of almost anything the
    # finder proposes (a mouse, a face), its peaks are not. 0 for unrelated photos (one chance each)
    birth_confidence: float = 0.3
    # frames until the finder looks again after a proposed hand was not born: while one hand is
    # tracked, a second one refused on its first frame would otherwise wait `redetect_every`
    unborn_retry: int = 3
    # with every track slot taken, a found hand no track covers replaces the track DetNet
    # believes least (running mean heatmap peak) when its own peak is this much higher (None:
    # never): otherwise a desk object or a forearm that outlived its hand keeps the slot
    evict_margin: float | None = 0.2
    # a track tried on the centre square (the CENTRE fallback) is born only from this mean
    # heatmap peak on, even where birth_confidence is lower: the centre of a photo is not a hand
    centre_confidence: float = 0.3
    # two tracks both at least this sure to be hands (running mean heatmap peak) that read as the
    # same hand are a person's left and right: the one with the weaker side evidence turns (None:
    # off); false tracks (desk objects, a forearm) stay below it, so they cannot turn a real hand
    opposite_hands: float | None = 0.4
    # a track's crop turns in whole steps of this many degrees (0: any angle; None: never) so its
    # hand appears upright, wrist below the middle finger's base, from its last 2D joints; a new
    # track tries the four quarter turns. Unturned, a hand hanging down read 2-4x worse
    upright_step: float | None = 90.0
    # which way is up for that turn: "wrist_knuckle", the wrist -> middle finger's base (0 -> 9) of
    # the last joints; "palm", that plus the normal of the knuckle line (crops.palm_angle), which
    # stays as long as the palm is wide where the fingers point at or away from the camera. "palm"
    # is off: held back (10 runs, session 58) median 0.097 against 0.099, PCK 0.574 against 0.572,
    # found 87.5% against 88.7 (the foreshortened Kirichovka__want read worse, 0.223 against 0.200;
    # the small-handed signer rodrmilano00__ROSA better, 0.142 against 0.206). With the DetNet trained
    # for it (models/detnet_lite0_palm_int8.onnx): median 0.091, PCK 0.584, but 0.025 false hands a frame
    # against 0.020 (session 58; not the default)
    turn_by: str = "wrist_knuckle"
    # a tracked hand whose mean heatmap peak on this frame's crop is below this (None: never) is
    # also read at the three other quarter turns of its crop (without the side), as a new track
    # is, and the turn DetNet is surest of is kept: a hand read wrong way round turns its next
    # crop by its own wrong joints and stays wrong. 3 crops more a check. Off: on the training
    # people's clips the median did not move and found fell 0.3-1.5 points; on the held-back
    # clips (0.4, 10 runs) median 0.109 against 0.110, PCK 0.559 against 0.550 (session 48); at
    # 0.6 every 6th frame, median 0.108, PCK 0.558, side 86.5% against 83.7, found 87.6% against
    # 88.2 (session 51)
    turn_check_below: float | None = None
    turn_check_every: int = 5           # frames of a track between two turn checks at least (>= 1)
    # with a DetNet file that has an angle head (a `hand_angle` output: training/angle_head.py), a
    # crop turns by the head's angle where its (cos, sin) is at least this long (the head's
    # certainty) instead of by the keypoints' angle, and a new hand the head is sure of is read at
    # the head's turn rather than at all four quarter turns (None: the keypoints' angle, four turns).
    # On held-back crops turned at random the head's angle is more than 45 degrees off on 6% of
    # crops at 0.5 and up, the keypoints' on 30%. Off: tracked at 0.5 (runs/angle's file, session 52),
    # the held-back clips' median 0.112 against 0.110, PCK 0.554 against 0.550, false hands 0.037
    # against 0.041, howiema 040 11.76 px against 11.92
    turn_from_head: float | None = None
    # with turn_from_head, tracked crops turn by the head too (false: only a new hand's first crops;
    # the training people's clips then found 91.5% against 92.2, session 52)
    turn_tracked_from_head: bool = True
    # with turn_from_head, a new hand is read at the head's turn (false: at all four, as without it)
    turn_births_from_head: bool = True
    # with turn_from_head, a tracked crop turns by the running mean of the head's (cos, sin) in the
    # frame, each frame's reading weighing this much (None: this frame's alone); its length is then
    # what turn_from_head bounds: readings that disagree from frame to frame shorten it. At 0.3 with
    # births as without the head (session 52): held-back median 0.112 against 0.110, howiema 040
    # 12.02 px against 11.92
    turn_head_memory: float | None = None
    # a tracked crop keeps its turn while the head's angle is within this many degrees of it (45:
    # the head's nearest quarter turn every frame): unbiased, the head's angle of a hand pointing
    # about diagonally crosses 45 degrees back and forth, and each crossing turned the crop (one
    # signer's clip: 100 turns in 240 frames against 4 by the joints; 77 at 60, and the training
    # people's clips found 91.5% against 92.2, session 52)
    turn_head_margin: float = 60.0
    # weight of the finder's side against one DetNet reading (0: DetNet's alone)
    finder_handedness: float = 0.3
    # every this many frames of a track (and on its first), DetNet also reads its crop flipped
    # the other way and the handedness head's answer there votes too (0 or None: never): the
    # head is biased on views unlike its training data, and on a crop and its mirror image its
    # two answers share the bias, which their mean cancels
    mirror_vote_every: int | None = 6
    # with a second network for the side (DetNetRunner `side`, the default pair), a tracked
    # hand's side is read on a track's first crops, its mirror votes and every this many frames
    # only (None: every frame; above mirror_vote_every, the votes alone): spread out, a track's `handedness_memory` readings span longer than one view's
    # errors (held-back clips: side 87.7% against 81.7% read every frame; session 37)
    side_every: int | None = 6
    # a new track's reading is the per-coordinate median over its crop and this many variants
    # (TEST_TIME_VARIANTS: a little larger, smaller, turned; 0 or None: off): for photos, read once
    test_time_crops: int | None = 0
    # a re-seed must convince DetNet: its mean heatmap peak on the found box's crop at least the
    # track's running peak minus this (None: every re-seed is taken); a track swollen around an
    # exploded prediction holds boxes of other things
    reseed_margin: float | None = 0.2
    # the same median for every tracked hand on every frame (0 or None: off): K more crops a hand
    tracked_test_time_crops: int | None = 0
    # a tracked hand whose joints' box changed size by more than this fraction since the last
    # frame is read again on `second_look_crops` variants, median kept (0 or None: never): a hand
    # does not change size that fast, and such readings were often wrong
    second_look: float | None = 0.1
    second_look_crops: int = 2          # variants of its crop a second look reads (0..6)
    # a track's side is the running mean logit of about its last this many readings: long enough
    # to outlast the head's bad stretches on a view, short enough that a wrong start turns
    handedness_memory: int = HANDEDNESS_MEMORY
    # "left" or "right": every hand is that side (one known hand, e.g. the one driving a robot
    # hand): no wrong-side reading, no mirror vote to pay for; None: each track's side is read
    handedness: str | None = None
    # a track whose side turns on this frame's readings is read again, mirrored for its new side:
    # otherwise the hand published as left was read as a right one, its 2D 2-3x worse and its 3D
    # the other hand's; a photo has no next frame to mend it. One crop more per turn
    settle_side: bool = True
    # each track's published 2D joints go through a One Euro filter on the joints / the hand's
    # size: cut-off smooth_min_cutoff Hz at rest (0 or None: unfiltered), rising by smooth_beta Hz
    # per hand size a second. 2 Hz and 16 halve the shake and leave the error to MediaPipe's
    # labels no worse on the training people's clips (research/keypoint_smoothing.py)
    smooth_min_cutoff: float | None = 2.0
    smooth_beta: float = 16.0           # the filter's cut-off rise, Hz per hand size a second of speed

    def __post_init__(self):
        if self.handedness not in (None, "left", "right"):
            raise ValueError(f"handedness must be 'left', 'right' or None, got {self.handedness!r}")
        for name in ("test_time_crops", "tracked_test_time_crops", "second_look_crops"):
            _variant_count(name, getattr(self, name))
        if self.turn_from_head is not None and self.turn_from_head < 0:
            raise ValueError(f"turn_from_head must be >= 0 or None, got {self.turn_from_head}")
        if self.turn_head_memory is not None and not 0.0 < self.turn_head_memory <= 1.0:
            raise ValueError(f"turn_head_memory must be in (0, 1] or None, got {self.turn_head_memory}")
        if not 45.0 <= self.turn_head_margin <= 180.0:
            raise ValueError(f"turn_head_margin must be 45..180 degrees, got {self.turn_head_margin}")
        if self.edge_joints is not None and not 1 <= self.edge_joints <= 21:
            raise ValueError(f"edge_joints must be 1..21 or None, got {self.edge_joints}")
        if self.turn_by not in HAND_ANGLES:
            raise ValueError(f"turn_by must be one of {', '.join(HAND_ANGLES)}, got {self.turn_by!r}")
        if self.turn_check_every < 1:
            raise ValueError(f"turn_check_every must be >= 1, got {self.turn_check_every}")
        if self.redetect_every < 0 or (self.redetect_every_full or 0) < 0:
            raise ValueError(f"redetect_every and redetect_every_full must be >= 0, got {self.redetect_every}, "
                             f"{self.redetect_every_full}")
        if self.finder_waits < 0:
            raise ValueError(f"finder_waits must be >= 0, got {self.finder_waits}")
        if (self.smooth_min_cutoff or 0.0) < 0 or self.smooth_beta < 0:
            raise ValueError(f"smooth_min_cutoff and smooth_beta must be >= 0, got {self.smooth_min_cutoff}, "
                             f"{self.smooth_beta}")

    @classmethod
    def nullable(cls) -> set[str]:
        """The settings None turns off (their type says `| None`)."""
        return {f.name for f in dataclasses.fields(cls) if "None" in str(f.type)}


class HandDetector:
    """Hands of a frame sequence; see the module doc.

    finder: a HandFinder (or None: the centre square crop of the frame is tried instead, as
    the paper's release did); detnet: a DetNetRunner. presence_threshold: below it a track
    is lost; redetect_every: frames between finder runs while fewer than max_hands hands
    are tracked (redetect_every_full: while max_hands are); crop_scale: crop side / joint-box
    side; min_confidence: below this mean heatmap peak a track is lost too; birth_confidence:
    a found hand becomes a track only if DetNet's mean heatmap peak on its refined crop
    reaches this (the two thresholds are a hysteresis, chosen on training-side held-out clips
    by scripts/detector_thresholds.py; 0.3 is for video, where a hand refused on one frame is
    proposed again `unborn_retry` frames later: for unrelated photos, one chance each, use 0,
    or PHOTO_SETTINGS with HandDetector.load). Every setting is explained beside its
    DetectorSettings field.
    """

    def __init__(self, detnet, finder=None, fallback=None, grey_finder=None, grey_detnet=None,
                 settings: DetectorSettings | None = None, **changes):
        """detnet, finder, fallback, grey_finder, grey_detnet: the networks (see the class doc);
        settings: a DetectorSettings (None: the defaults), with `changes` (its field names,
        e.g. max_hands=1) applied on top; TypeError naming an unknown one."""
        try:
            settings = dataclasses.replace(settings or DetectorSettings(), **changes)
        except TypeError:
            unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(DetectorSettings)})
            raise TypeError(f"HandDetector has no setting {', '.join(unknown)} (DetectorSettings' fields are "
                            f"its settings)") from None
        self.settings = settings
        # each setting is an attribute of the same name (DetectorSettings says what it does);
        # a few are read in the form the code uses: None as 0, the retry at most the finder's period
        for f in dataclasses.fields(DetectorSettings):
            setattr(self, f.name, getattr(settings, f.name))
        self.unborn_retry = min(settings.unborn_retry, settings.redetect_every)
        self.finder_beside = settings.finder_beside and cores() > 1      # on one core it would wait its turn
        for runner in (detnet, grey_detnet):
            if runner is not None and hasattr(runner, "pin_helper"):
                runner.pin_helper = settings.pin_threads
        self.test_time_crops = settings.test_time_crops or 0
        self.tracked_test_time_crops = settings.tracked_test_time_crops or 0
        self.second_look = settings.second_look or 0.0
        self.smooth_min_cutoff = settings.smooth_min_cutoff or 0.0
        self.detnet, self.finder = detnet, finder
        # px: the side of the crops cut for DetNet, as its file says (a fake runner: CROP)
        self.crop_size = getattr(detnet, "crop_side", CROP)
        # the finder and the DetNet for grey frames (a mono or IR camera: hand_finder.is_grey,
        # checked whenever the finder runs; None: `finder` / `detnet` on every frame)
        self.grey_finder, self.grey_detnet = grey_finder, grey_detnet
        self.grey_frames = False
        # tried on a frame where the finder's boxes gave no track: a second HandFinder, or
        # CENTRE (the centre square of the frame, as the paper's release did: a close-up
        # photo whose hand fills the frame, which the finder, trained on hands in scenes,
        # can miss)
        self.fallback = fallback
        self.frame_time = 0.0
        self.tracks: list[Track] = []
        self.next_id = 0
        self.frames_since_find = 0
        self.lost_last_frame = False
        self._beside_pool = None    # the finder's thread when it runs beside the crops (made on first use)
        self.stats = {"frames": 0, "finder_runs": 0, "crops": 0, "reseeds": 0, "unborn": 0, "fallback_runs": 0,
                      "evictions": 0, "handedness_turns": 0, "second_looks": 0, "turn_checks": 0,
                      "side_rereads": 0, "grey_finder_runs": 0, "head_turns": 0}

    @classmethod
    def load(cls, detnet=None, finder=None, threads=1, fallback=None, grey_finder=None, grey_detnet=None,
             side_detnet=None, **kwargs):
        """Networks from files, named as HandTracker names them (None: the bundled ones;
        grey_finder / grey_detnet "none": the one finder / DetNet on grey frames too, and none
        for grey frames where finder / detnet names another file than the bundled one, unless
        given; fallback: a finder file or CENTRE; side_detnet: a DetNet whose handedness head
        gives the side, DetNetRunner's `side`). threads: onnxruntime intra-op threads per
        network, and OpenCV's thread count, which is process-wide: the crops and the finder's
        resize are too small to gain from threads, whose hand-offs cost ~0.6 ms of CPU per
        frame with OpenCV's default (one per core) here."""
        cv2.setNumThreads(threads)
        if grey_finder is None and finder is None:
            grey_finder = GREY_PATH
        if grey_detnet is None and detnet in (None, "int8"):
            grey_detnet = DETNET_GREY
        load_finder = lambda path: HandFinder.load(path, threads=threads) if path not in (None, "none") else None  # noqa: E731
        return cls(DetNetRunner.load(detnet, threads=threads, side_path=side_detnet),
                   HandFinder.load(finder, threads=threads) if finder != "none" else None,
                   fallback=fallback if fallback in (None, CENTRE) else load_finder(fallback),
                   grey_finder=load_finder(grey_finder),
                   grey_detnet=DetNetRunner.load(grey_detnet, threads=threads) if grey_detnet not in (None, "none") else None,
                   **kwargs)

    def reset(self):
        self.tracks.clear()
        self.frames_since_find = 0
        self.lost_last_frame = False

    # -------------------------------------------------------------- finding
    def _should_find(self):
        if not self.tracks or self.lost_last_frame:
            return True
        full = len(self.tracks) >= self.max_hands
        period = (self.redetect_every_full or self.redetect_every) if full else self.redetect_every
        if self.frames_since_find < period:
            return False
        if full and not self.reseed_iou > 0:   # every slot held, no re-seeding
            return False
        return self.frames_since_find >= period + self.finder_waits or not self._side_read_due()

    def _vote_due(self, track):
        """Is `track` due a mirror vote on this frame (`mirror_vote_every`)?"""
        return bool(self.mirror_vote_every) and not track.fixed_side and track.age % self.mirror_vote_every == 0

    def _side_due(self, track):
        """Is `track` due a side reading on this frame (`side_every`; None: every frame)?"""
        return not self.side_every or track.age % self.side_every == 0

    def _side_read_due(self):
        """Does this frame read a track's side at a cost (`_run_voting`): a mirror vote (a crop
        more), or a side reading where a second network reads the side at intervals?"""
        paired = self.side_every and getattr(self.detnet, "side", None) is not None
        return any(self._vote_due(t) or (paired and self._side_due(t)) for t in self.tracks)

    def _frame_finder(self, finder=None):
        """The finder to run on this frame: `finder` when given, else the grey one on grey
        frames, else self.finder (None or CENTRE: the centre square)."""
        if finder is None and self.grey_finder is not None and self.grey_frames:
            return self.grey_finder
        return finder or self.finder

    def _count_finder_run(self, finder):
        """A finder run on this frame (a grey one counted too): the finder's period starts again."""
        self.stats["finder_runs"] += 1
        self.stats["grey_finder_runs"] += finder is not None and finder is self.grey_finder
        self.frames_since_find = 0

    def _boxes_wanted(self):
        # with every slot taken, one box more than the tracks: a hand they do not hold may evict one
        return self.max_hands + (self.evict_margin is not None and len(self.tracks) >= self.max_hands)

    def _find(self, image, finder=None, found=None):
        """New tracks for found hands that no track covers, and the tracks re-seeded: both
        are refined from their first prediction. finder: the one to run (None: this frame's,
        _frame_finder; the fallback after a frame that found nothing); found:
        the FoundHands of a finder run beside this frame's crops, instead of a run now."""
        h, w = image.shape[:2]
        centre = False
        if found is None:
            finder = self._frame_finder(finder)
            self._count_finder_run(finder)
            centre = finder is None or finder == CENTRE
            found = [] if centre else finder.find(image, self.finder_threshold, self._boxes_wanted())
        found = [(f.box, f.score, f.right_prob) for f in found]
        if centre:
            half = min(h, w) / 2 / self.crop_scale      # the joint box whose crop is the centre square
            found = [(np.array([w / 2 - half, h / 2 - half, w / 2 + half, h / 2 + half]), 0.5, 0.5)]
        if self.handedness is not None:             # the given side, not the finder's guess
            found = [(box, score, float(self.handedness == "right")) for box, score, _ in found]
        new, reseeded, fresh = [], [], []
        # each found box first goes to the track whose joints it overlaps best (one box per
        # track): a second hand close beside a tracked one lies inside that track's crop, but
        # it is not that track's hand
        overlap = {}
        for k, (box, _, _) in enumerate(found):
            for t in self.tracks:
                if t.uv is not None:
                    overlap[k, t.track_id] = box_iou(square_box(t.uv), box)[0, 0]
        owner = {}
        for (k, tid), iou in sorted(overlap.items(), key=lambda kv: -kv[1]):
            if iou >= MATCH_IOU and k not in owner and tid not in owner.values():
                owner[k] = tid
        for k, (box, score, right_prob) in enumerate(found):
            if k in owner:
                covering = [t for t in self.tracks if t.track_id == owner[k]]
            else:   # a track that no box matched, whose crop holds this box: it may have slid off the hand
                covering = [t for t in self.tracks if t.track_id not in owner.values() and self._covers(t.crop, box)]
            if covering:
                t = covering[0]
                owner[k] = t.track_id
                if self.finder_handedness:
                    t.add_handedness(right_prob, weight=0.5 * self.finder_handedness)
                if t.uv is not None and overlap.get((k, t.track_id), 0.0) < self.reseed_iou and \
                        self._reseed_believed(image, box, right_prob, t):
                    # the track's joints no longer match the hand the finder sees in its crop
                    # (a track sliding up the forearm): start the crop again from the finder's box
                    t.crop = crop_for_box(box, not t.is_right, self.crop_scale, self.crop_size)
                    t.velocity, t.uv, t.smoother, t.head_dir = np.zeros(2), None, None, None
                    self.stats["reseeds"] += 1
                    reseeded.append(t)
                continue
            fresh.append((box, right_prob))
        free = self.max_hands - len(self.tracks)
        for box, right_prob in fresh[:max(free, 0)]:
            new.append(self._new_track(box, right_prob))
            if centre:
                new[-1].birth_confidence = max(self.birth_confidence, self.centre_confidence)
        self.tracks.extend(new)
        if free <= 0 and fresh and self.evict_margin is not None:
            new += self._evict(image, fresh, reseeded)
        return new + reseeded

    def _found_peaks(self, image, found):
        """(M,) DetNet's mean heatmap peak on the crop of each found (box, right_prob)."""
        crops = [crop_for_box(box, right_prob < 0.5, self.crop_scale, self.crop_size) for box, right_prob in found]
        return self._run(image, crops, read_side=False)["confidence"].mean(axis=1)

    def _reseed_believed(self, image, box, right_prob, track):
        """Whether DetNet's mean heatmap peak on the crop of a found box is at least the
        track's running peak minus `reseed_margin` (always, with no margin; and without a read
        where that bound is not above 0, which every peak reaches)."""
        return self.reseed_margin is None or track.confidence - self.reseed_margin <= 0.0 or \
            self._found_peaks(image, [(box, right_prob)])[0] >= track.confidence - self.reseed_margin

    def _new_track(self, box, right_prob):
        track = Track(self.next_id, crop_for_box(box, right_prob < 0.5, self.crop_scale, self.crop_size),
                      memory=self.handedness_memory)
        if self.handedness is not None:
            track.right_logit, track.fixed_side = (1.0 if self.handedness == "right" else -1.0), True
        if self.finder_handedness:
            track.add_handedness(right_prob, weight=self.finder_handedness)
        self.next_id += 1
        return track

    def _evict(self, image, fresh, keep):
        """New tracks for found boxes `fresh` ((box, right_prob) list) that DetNet believes
        more than the tracks they replace (mean heatmap peak on the box's crop above the
        weakest track's running peak by `evict_margin`); tracks in `keep` stay. Where that bound
        is above 1, which no heatmap peak exceeds (a sigmoid's), nothing is read: a sure track
        (running peak 0.8 and up) costs the finder's frame no DetNet read of the found boxes."""
        held = [t for t in self.tracks if t not in keep]
        if not held or min(t.confidence for t in held) + self.evict_margin > 1.0:
            return []
        peak = self._found_peaks(image, fresh)
        born = []
        for i in np.argsort(-peak, kind="stable"):
            held = [t for t in self.tracks if t not in keep and t not in born]
            if not held:
                break
            weakest = min(held, key=lambda t: t.confidence)
            if peak[i] < weakest.confidence + self.evict_margin:
                break
            born.append(self._new_track(*fresh[i]))
            self.tracks[self.tracks.index(weakest)] = born[-1]
            self.stats["evictions"] += 1
        return born

    @staticmethod
    def _covers(crop, box):
        centre = (box[:2] + box[2:]) / 2
        cb = crop.box
        inside = cb[0] <= centre[0] <= cb[2] and cb[1] <= centre[1] <= cb[3]
        return inside or box_iou(cb, box)[0, 0] >= 0.3

    # -------------------------------------------------------------- per frame
    def _run(self, image_bgr, crops, flipped=(), read_side=True):
        """DetNet's outputs on the CropTransforms `crops` of a frame, then on the crops with
        indices `flipped` mirrored the other way (in the same batch, after the others);
        read_side=False: a side network (DetNetRunner `side`) is not run, handedness NaN."""
        detnet = self.grey_detnet if self.grey_frames and self.grey_detnet is not None else self.detnet
        # cut from the BGR frame and reverse the channels of the crops only: cutting from a
        # reversed-channel view of the frame made OpenCV copy the whole frame for each crop (and
        # OpenCV's colour conversion and flip cost a tenth of numpy's strided copies)
        cut = lambda part: [cv2.cvtColor(c.cut(image_bgr), cv2.COLOR_BGR2RGB) for c in part]   # noqa: E731
        half = len(crops) // 2 if getattr(detnet, "beside", False) else 0
        if half:    # the later half cut on DetNet's second thread meanwhile (OpenCV lets go of the GIL)
            later = detnet.second_thread().submit(cut, crops[half:])
            rgb = cut(crops[:half]) + later.result()
        else:
            rgb = cut(crops)
        pixels = np.stack(rgb + [cv2.flip(rgb[i], 1) for i in flipped])
        self.stats["crops"] += len(pixels)
        # only a pair of networks (DetNetRunner `side`) has a side read to skip, and reads the
        # flipped crops (mirror votes, whose handedness alone is wanted) with the side network only
        out = detnet(pixels, read_side=read_side, side_only=len(flipped)) if getattr(detnet, "side", None) is not None \
            else detnet(pixels)
        if "uv_peak" not in out:            # a file exported before session 17
            out["uv_peak"] = out["uv"].copy()
        return out

    def process(self, image_bgr, t=None):
        """HandKeypoints hands of one BGR frame (H,W,3) uint8, sorted by track id. t: its
        capture time in seconds, for the 2D joints' filter (None: 1/30 s after the last frame)."""
        if not self.pin_threads or not (self.finder_beside or getattr(self.detnet, "beside", False)):
            return self._process(image_bgr, t)
        with off_helper_cpu():
            return self._process(image_bgr, t)

    def _process(self, image_bgr, t):
        self.frame_time = self.frame_time + 1 / 30 if t is None else float(t)
        self.stats["frames"] += 1
        self.frames_since_find += 1
        searched = self._should_find()
        if searched and (self.grey_finder is not None or self.grey_detnet is not None):
            self.grey_frames = is_grey(image_bgr)       # a camera's frames do not turn grey between finder runs
        finder = self._frame_finder() if searched else None
        if searched and self.finder_beside and self.tracks and hasattr(finder, "find"):   # not CENTRE
            if self._beside_pool is None:
                self._beside_pool = ThreadPoolExecutor(1, thread_name_prefix="finder",
                                                       initializer=keep_on_helper_cpu if self.pin_threads else None)
            self._count_finder_run(finder)
            running = self._beside_pool.submit(finder.find, image_bgr, self.finder_threshold, self._boxes_wanted())
            tracks = list(self.tracks)
            read = self._run_voting(image_bgr, tracks)  # the tracked crops while the finder runs
            hands = self._track(image_bgr, self._find(image_bgr, found=running.result()), (tracks, read))
        else:
            hands = self._track(image_bgr, self._find(image_bgr, finder) if searched else [])
        if searched and not self.tracks and self.fallback is not None:   # nothing became a track
            self.stats["fallback_runs"] += 1
            hands = self._track(image_bgr, self._find(image_bgr, self.fallback))
        return hands

    def _track(self, image_bgr, new, read=None):
        """DetNet on every track's crop (the `new` ones re-cut once, from their own first
        prediction): the frame's hands. read: (tracks, DetNet's outputs on their crops) read
        already on this frame, beside the finder; those of them still tracked and not in `new`
        (re-seeded) keep that reading."""
        self.lost_last_frame = False
        if not self.tracks:
            return []
        out = self._run_voting(image_bgr, self.tracks) if read is None else self._read_with(image_bgr, new, *read)
        idx = [i for i, t in enumerate(self.tracks) if t in new]
        if self.upright_step is not None and idx:
            unsure = self._turn_by_head(image_bgr, idx, out)
            if unsure:
                self._take_best_quarter_turn(image_bgr, unsure, out)
        if idx:                                     # a new track's crop from its own prediction
            for i in idx:
                t = self.tracks[i]
                if out["presence"][i] >= self.presence_threshold:
                    t.add_head_reading(float(out["handedness"][i]), t.crop.mirrored)
                    uv = t.crop.to_frame(out["uv_peak"][i])
                    angle = self._head_angle(t.crop, out, i)
                    t.crop = crop_for_joints(uv, not t.is_right, self.crop_scale, self.upright_step, self.crop_size,
                                             self._joints_angle(uv) if angle is None else angle)
            again = self._run_voting(image_bgr, [self.tracks[i] for i in idx])   # a new track votes again here
            for k, i in enumerate(idx):
                for key in out:
                    out[key][i] = again[key][k]
        if self.test_time_crops and idx:
            self._median_over_nearby_crops(image_bgr, idx, out, self.test_time_crops)
        tracked = [i for i in range(len(self.tracks)) if i not in idx]
        if self.tracked_test_time_crops and tracked:
            self._median_over_nearby_crops(image_bgr, tracked, out, self.tracked_test_time_crops)
        elif self.second_look and tracked:
            jumped = [i for i in tracked if self._size_jumped(self.tracks[i], out["uv_peak"][i])]
            if jumped:
                self.stats["second_looks"] += len(jumped)
                self._median_over_nearby_crops(image_bgr, jumped, out, self.second_look_crops)
        if self.turn_check_below is not None and self.upright_step is not None and tracked:
            self._check_turns(image_bgr, tracked, out)
        counted = set()
        if self.settle_side:
            counted = self._settle_sides(image_bgr, idx, out, self.test_time_crops) | \
                self._settle_sides(image_bgr, tracked, out, self.tracked_test_time_crops)
        hands, keep = [], []
        for i, t in enumerate(self.tracks):
            presence, confidence = float(out["presence"][i]), float(np.mean(out["confidence"][i]))
            birth = self.birth_confidence if t.birth_confidence is None else t.birth_confidence
            if t.age == 0 and confidence < birth:   # not a hand after all: no loss to report
                self.stats["unborn"] += 1
                self.frames_since_find = max(self.frames_since_find, self.redetect_every - self.unborn_retry)
                continue
            if presence < self.presence_threshold or confidence < self.min_confidence:
                self.lost_last_frame = True
                continue
            # the track follows the heatmap peaks; the hand published is read out finer (uv)
            uv, followed = t.crop.to_frame(out["uv"][i]), t.crop.to_frame(out["uv_peak"][i])
            if not self._plausible(followed, image_bgr.shape, self.edge_joints):
                self.lost_last_frame = True
                continue
            # the wire contract (messages/HandKeypoints.json): joint 9 at the origin, |0-9| = 1;
            # DetNet's location-map read-out is only near that
            xyz = normalize_joints(out["xyz"][i])
            if not np.all(np.isfinite(xyz)):
                self.lost_last_frame = True
                continue
            if t.crop.mirrored:
                xyz = mirror_points(xyz)
            if t.crop.angle:
                xyz = t.crop.to_frame_axes(xyz)
            if i not in counted:
                t.add_head_reading(float(out["handedness"][i]), t.crop.mirrored)
            if t.uv is not None:
                t.velocity = np.median(followed - t.uv, axis=0)
            t.uv, t.age = followed, t.age + 1
            uv = self._smoothed(t, uv)
            # a few frames of memory: one blurred frame must not let a desk object evict the hand
            t.confidence = confidence if t.age == 1 else t.confidence + 0.3 * (confidence - t.confidence)
            hands.append({"track_id": t.track_id, "handedness": "right" if t.is_right else "left",
                          "score": presence, "bbox": t.crop.box.astype(np.float32),
                          "uv": uv.astype(np.float32), "confidence": np.asarray(out["confidence"][i], np.float32),
                          "xyz_rel": xyz.astype(np.float32)})
            t.crop = self._next_crop(t, followed, self._tracked_head_angle(t, out, i))
            keep.append(t)
        self.tracks = keep
        hands = self._drop_duplicates(hands, {t.track_id: t.uv for t in keep})
        if self.opposite_hands is not None and self.handedness is None:
            self._one_left_one_right()
        return sorted(hands, key=lambda h: h["track_id"])

    def _read_with(self, image_bgr, new, read_tracks, read):
        """DetNet's outputs on every track's crop in self.tracks' order: those of `read_tracks`
        (outputs `read`) as read, but for the tracks in `new`; the others read now."""
        row = {id(t): k for k, t in enumerate(read_tracks) if not any(t is n for n in new)}
        rest = [t for t in self.tracks if id(t) not in row]
        now, later = (self._run_voting(image_bgr, rest) if rest else {}), {id(t): k for k, t in enumerate(rest)}
        rows = [(read, row[id(t)]) if id(t) in row else (now, later[id(t)]) for t in self.tracks]
        return {key: np.stack([o[key][r] for o, r in rows]) for key in read}

    def _run_voting(self, image_bgr, tracks):
        """DetNet's outputs on the crops of `tracks`; the crops of those due a mirror vote
        (`mirror_vote_every`; a new track on each of its first frame's crops) are also read
        flipped, and the handedness head's answer there goes into their running handedness."""
        due = [i for i, t in enumerate(tracks) if self._vote_due(t)]
        read_side = bool(due) or any(self._side_due(t) for t in tracks)
        out = self._run(image_bgr, [t.crop for t in tracks], due, read_side)
        n = len(tracks)
        for k, i in enumerate(due):     # the head on the crop mirrored the other way
            tracks[i].add_head_reading(float(out["handedness"][n + k]), not tracks[i].crop.mirrored)
        return {key: v[:n] for key, v in out.items()}

    def _settle_sides(self, image_bgr, idx, out, test_time_crops=0):
        """Tracks (indices `idx`; `out` DetNet's outputs, replaced in place) take this frame's
        last handedness reading now; those whose side is then no longer the one their crop was
        mirrored for are read again, mirrored for their side (and on `test_time_crops`
        variants), and the re-read casts no vote: the hand published is read as the side it
        is published as. -> the indices whose reading is counted."""
        idx = [i for i in idx if out["presence"][i] >= self.presence_threshold]    # the rest are dropped
        for i in idx:
            self.tracks[i].add_head_reading(float(out["handedness"][i]), self.tracks[i].crop.mirrored)
        turned = [i for i in idx if self.tracks[i].crop.mirrored == self.tracks[i].is_right]
        self.stats["side_rereads"] += len(turned)
        if turned:
            for i in turned:
                self.tracks[i].crop = replace(self.tracks[i].crop, mirrored=not self.tracks[i].is_right)
            again = self._run(image_bgr, [self.tracks[i].crop for i in turned], read_side=False)
            for k, i in enumerate(turned):
                for key in out:
                    out[key][i] = again[key][k]
            if test_time_crops:
                self._median_over_nearby_crops(image_bgr, turned, out, test_time_crops)
        return set(idx)

    def _check_turns(self, image_bgr, idx, out):
        """Tracked hands (indices `idx`) that DetNet doubts on this frame (mean heatmap peak
        below `turn_check_below`), at most once every `turn_check_every` frames each, try the
        other quarter turns of their crop (_take_best_quarter_turn)."""
        doubted = [i for i in idx if out["presence"][i] >= self.presence_threshold and
                   out["confidence"][i].mean() < self.turn_check_below and
                   self.tracks[i].age - self.tracks[i].turn_checked >= self.turn_check_every]
        for i in doubted:
            self.tracks[i].turn_checked = self.tracks[i].age
        if doubted:
            self.stats["turn_checks"] += len(doubted)
            self._take_best_quarter_turn(image_bgr, doubted, out, read_side=False)

    def _head_angle(self, crop, out, i):
        """The hand's angle in the frame (radians) from the angle head's reading `out` row i on
        `crop`, where `turn_from_head` is set, the file has the head and it is that sure; else None."""
        if self.turn_from_head is None or "hand_angle" not in out:
            return None
        cos_sin = out["hand_angle"][i]
        return head_angle_in_frame(crop, cos_sin) if np.hypot(*cos_sin) >= self.turn_from_head else None

    def _tracked_head_angle(self, track, out, i):
        """The angle (radians, in the frame) a tracked hand's next crop turns by, from the angle
        head (`out` row i, read on track.crop), through its running mean (`turn_head_memory`): the
        crop's own where the head is within `turn_head_margin` of it; None (the joints' angle)
        where there is no head, turn_from_head or turn_tracked_from_head is off, or the (mean)
        reading is shorter than turn_from_head."""
        if self.turn_from_head is None or not self.turn_tracked_from_head or "hand_angle" not in out:
            return None
        if self.turn_head_memory is None:
            angle = self._head_angle(track.crop, out, i)
        else:
            a = head_angle_in_frame(track.crop, out["hand_angle"][i])
            seen = float(np.hypot(*out["hand_angle"][i])) * np.array([math.cos(a), math.sin(a)])
            mean = seen if track.head_dir is None else track.head_dir + self.turn_head_memory * (seen - track.head_dir)
            track.head_dir = mean
            angle = math.atan2(mean[1], mean[0]) if np.hypot(*mean) >= self.turn_from_head else None
        if angle is not None and angle_apart(angle, track.crop.angle) <= math.radians(self.turn_head_margin):
            return track.crop.angle                 # near enough the crop's own turn: it stays
        return angle

    def _turn_by_head(self, image_bgr, idx, out):
        """New tracks (indices `idx`, `out` DetNet's outputs on their crops, replaced in place)
        whose angle head is sure (_head_angle) turn their crop to the head's turn (rounded to
        `upright_step`) and are read there, where that is not the crop's turn already. -> the
        indices of the others (no head, or unsure), for _take_best_quarter_turn."""
        if not self.turn_births_from_head:
            return list(idx)
        unsure, turned, crops = [], [], []
        for i in idx:
            angle = self._head_angle(self.tracks[i].crop, out, i)
            if angle is None:
                unsure.append(i)
                continue
            angle = rounded_turn(angle, self.upright_step)
            if angle_apart(angle, self.tracks[i].crop.angle) > 1e-6:
                turned.append(i)
                crops.append(replace(self.tracks[i].crop, angle=angle))
        self.stats["head_turns"] += len(idx) - len(unsure)
        if turned:
            more = self._run(image_bgr, crops)
            for k, i in enumerate(turned):
                self.tracks[i].crop = crops[k]
                for key in out:
                    out[key][i] = more[key][k]
        return unsure

    def _take_best_quarter_turn(self, image_bgr, idx, out, read_side=True):
        """Tracks (indices `idx` into self.tracks, `out` DetNet's outputs on their crops) take
        the quarter turn of their crop on which DetNet's mean heatmap peak is highest. A new
        track always does: the finder's box says nothing of which way the hand points, and the
        first prediction on an upside-down hand is too poor to turn it upright from; a doubted
        tracked hand does with `turn_check_below` (_check_turns). read_side=False: the turns
        are read without a side network and each hand keeps its own crop's side reading."""
        turns = [replace(self.tracks[i].crop, angle=self.tracks[i].crop.angle + k * math.pi / 2)
                 for i in idx for k in (1, 2, 3)]
        more = self._run(image_bgr, turns, read_side=read_side)
        peak = more["confidence"].mean(axis=1).reshape(len(idx), 3)
        for n, i in enumerate(idx):
            k = int(np.argmax(peak[n]))
            if peak[n, k] > out["confidence"][i].mean():
                self.tracks[i].crop = turns[3 * n + k]
                for key in out:
                    if read_side or key != "handedness":    # read_side False: the crop's own side reading stays
                        out[key][i] = more[key][3 * n + k]

    def _smoothed(self, track, uv):
        """uv (21,2) frame px of `track` at self.frame_time through its One Euro filter."""
        if not self.smooth_min_cutoff:
            return uv
        if track.smoother is None:
            track.smoother = OneEuroFilter(self.smooth_min_cutoff, self.smooth_beta)
            track.unit = max(float(np.max(np.ptp(uv, axis=0))), 1.0)
        return track.smoother(uv / track.unit, self.frame_time) * track.unit

    def _size_jumped(self, track, uv_crop):
        """Whether the joints read on the track's crop (uv_crop (21,2) crop px) span a box whose
        side differs from the last frame's by more than `second_look` of it."""
        if track.uv is None:
            return False
        uv = track.crop.to_frame(uv_crop)
        side, last = np.max(np.ptp(uv, axis=0)), np.max(np.ptp(track.uv, axis=0))
        return bool(np.isfinite(side) and last > 0 and abs(side / last - 1.0) > self.second_look)

    def _median_over_nearby_crops(self, image_bgr, idx, out, k):
        """Tracks (indices `idx` into self.tracks; `out` DetNet's outputs on their
        crops, replaced in place): each reading becomes the per-coordinate median of DetNet's
        on its crop and on `k` variants of it (TEST_TIME_VARIANTS), 2D in
        frame px and 3D in the frame camera's axes, mapped back to the track's crop, and the
        handedness the mean logit. Presence and heatmap peaks stay the crop's own: which
        hands are born does not change (a turned variant's peaks are lower)."""
        crops = [c for i in idx for c in nearby_crops(self.tracks[i].crop, k)]
        more = self._run(image_bgr, crops, read_side=not np.isnan(out["handedness"][idx]).any())
        for n, i in enumerate(idx):
            own = self.tracks[i].crop
            views = [own] + crops[n * k:(n + 1) * k]
            rows = [(out, i)] + [(more, n * k + j) for j in range(k)]
            for key in ("uv", "uv_peak"):
                out[key][i] = own.to_crop(np.median([c.to_frame(o[key][r]) for c, (o, r) in zip(views, rows)], axis=0))
            xyz = np.median([crop_to_frame_xyz(c, normalize_joints(o["xyz"][r])) for c, (o, r) in zip(views, rows)],
                            axis=0)
            out["xyz"][i] = frame_to_crop_xyz(own, xyz)
            read = [o["handedness"][r] for o, r in rows if not np.isnan(o["handedness"][r])]
            out["handedness"][i] = sigmoid(np.mean(logit(read))) if read else np.nan

    def _one_left_one_right(self):
        """Two tracks DetNet believes are hands (running mean heatmap peak >= opposite_hands)
        that both read as the same hand: one person's two hands are a left and a right, so the
        one with the weaker handedness evidence turns, from the next frame's crop on (this
        frame's 3D was read as the hand it was cropped as)."""
        sure = [t for t in self.tracks if t.confidence >= self.opposite_hands]
        if len(sure) != 2 or sure[0].is_right != sure[1].is_right:
            return
        weaker = min(sure, key=lambda t: abs(t.right_logit))
        weaker.right_logit = -weaker.right_logit if weaker.right_logit else -1e-3
        weaker.crop = replace(weaker.crop, mirrored=not weaker.is_right)
        self.stats["handedness_turns"] += 1

    def _next_crop(self, track, uv, angle=None, max_change=1.33):
        """Next frame's crop from this frame's joints: moved on by half the last
        displacement; its side changes by at most a factor `max_change` per frame (a hand
        does not change size that fast: a collapsing or exploding prediction must not take
        the crop with it). angle: the hand's angle (the angle head's) to turn it by instead of
        the joints'."""
        uv = uv + 0.5 * track.velocity
        crop = crop_for_joints(uv, not track.is_right, self.crop_scale, self.upright_step, self.crop_size,
                               self._joints_angle(uv) if angle is None else angle)
        side = float(np.clip(crop.side, track.crop.side / max_change, track.crop.side * max_change))
        return CropTransform.around(crop.centre, side, crop.size, mirrored=crop.mirrored, angle=crop.angle)

    def _joints_angle(self, uv):
        """The hand's angle (radians, as hand_angle) from its joints (21,2) by `turn_by`, or None for
        crop_for_joints' own (the wrist -> middle finger's base)."""
        if self.turn_by != "wrist_knuckle" and np.all(np.isfinite(uv[PALM_ANGLE_JOINTS, :])):
            return float(HAND_ANGLES[self.turn_by](uv))
        return None

    @staticmethod
    def _plausible(uv, shape, edge_joints=None):
        """A hand whose joints uv (21,2) frame px are finite, no wider than twice the frame and
        centred inside it, or (edge_joints not None) with at least `edge_joints` joints inside it."""
        if not np.all(np.isfinite(uv)):
            return False
        h, w = shape[:2]
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        if np.max(hi - lo) > 2 * max(h, w):
            return False
        centre = (lo + hi) / 2
        if 0 <= centre[0] < w and 0 <= centre[1] < h:
            return True
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        return edge_joints is not None and int(inside.sum()) >= edge_joints

    def _drop_duplicates(self, hands, followed=None, iou=0.5, inside=0.7):
        """Two tracks on one hand (joint boxes with IoU >= `iou`, or the smaller box at
        least `inside` covered by the other): keep the higher score
        (ties: the older track). Judged on `followed` {track id: (21,2) joints the track
        follows} where given, else on the hands' published uv."""
        followed = followed or {h["track_id"]: h["uv"] for h in hands}
        order = sorted(hands, key=lambda h: (-h["score"], h["track_id"]))
        kept, kept_boxes = [], []
        for h in order:
            uv = followed[h["track_id"]]
            box = np.concatenate([uv.min(0), uv.max(0)])
            if kept_boxes:
                overlap = (box_iou(box, np.array(kept_boxes))[0] >= iou) | \
                          (box_overlap_of_smaller(box, np.array(kept_boxes)) >= inside)
                if overlap.any():
                    continue
            kept.append(h)
            kept_boxes.append(box)
        ids = {h["track_id"] for h in kept}
        if len(ids) < len(self.tracks):
            # two tracks had converged on one hand: the other hand (if any) was lost, so the
            # finder looks again next frame rather than `redetect_every` frames later
            self.lost_last_frame = True
        self.tracks = [t for t in self.tracks if t.track_id in ids]
        return kept
