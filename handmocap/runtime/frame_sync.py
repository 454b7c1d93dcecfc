"""Pairs camera frames with the hand messages derived from them, by header stamp (no bus).

A frame's /hand/pose comes later than its /camera/image (it went through detector and ik), so
frames wait here until their pose arrives. A frame is **ready** once its pose is in (and its
keypoints, or `grace_s` after the pose without them). It is **expired** (drawn without
overlay) when it will never get a pose:
- the pose stream has passed it: a pose with a later stamp arrived (one publisher's messages
  arrive in order, so the detector skipped this frame);
- or no pose arrived at all for `timeout_s` while it waited (no hand pipeline, or it stalled).
Waiting on a pipeline that is merely behind (a backlog of keep-all frames) never expires a frame.

Two ways out (`pop`):
- keep_all (a video file): every frame, in stamp order, each as soon as it and all before it
  are ready or expired. A frame the detector skipped (a latest-only detector on a live camera)
  is drawn with the previous frame's pose and keypoints when those are at most `hold_s` older
  (`Frame.held`), so a recording does not flicker between annotated and bare frames;
- live: only the newest ready frame; older frames are dropped (not drawn late). Expired frames
  are drawn only when no pose came for `timeout_s` (so a camera without a hand pipeline still
  shows), never when the detector merely skipped them (that would flicker).
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass


@dataclass
class Frame:
    stamp_ns: int
    image: dict                       # Image message
    info: dict | None = None          # CameraInfo of the same stamp, or the latest before it
    pose: dict | None = None          # HandPose message, None if it never came
    keypoints: dict | None = None     # HandKeypoints message, None if it never came
    arrived: float = 0.0              # receive time (s, monotonic)
    pose_arrived: float | None = None
    held: bool = False                # pose and keypoints are an earlier frame's (this one was skipped)


class FrameSync:
    def __init__(self, keep_all: bool, timeout_s: float = 1.0, grace_s: float = 0.05, max_frames: int = 300,
                 hold_s: float = 0.1):
        self.keep_all, self.timeout_s, self.grace_s, self.max_frames = keep_all, timeout_s, grace_s, max_frames
        self.hold_ns = int(hold_s * 1e9)
        self.last_paired: Frame | None = None   # the newest frame drawn with its own pose
        self.frames: OrderedDict[int, Frame] = OrderedDict()   # stamp -> frame, in arrival order
        self.poses: dict[int, tuple[dict, float]] = {}          # poses/keypoints whose image is not in (yet)
        self.keypoints: dict[int, dict] = {}
        self.infos: OrderedDict[int, dict] = OrderedDict()
        self.last_info: dict | None = None
        self.last_pose_stamp = -1
        self.last_pose_time: float | None = None
        self.emitted_stamp = -1
        self.overflowed = 0            # frames pushed out unpaired because the buffer was full

    # -- input ----------------------------------------------------------------------------
    def add_image(self, msg: dict, now: float) -> None:
        stamp = msg["header"]["stamp_ns"]
        if stamp <= self.emitted_stamp or stamp in self.frames:
            return                                        # older than what was drawn: too late
        f = Frame(stamp, msg, arrived=now)
        if stamp in self.poses:
            f.pose, f.pose_arrived = self.poses.pop(stamp)
        f.keypoints = self.keypoints.pop(stamp, None)
        self.frames[stamp] = f

    def add_info(self, msg: dict) -> None:
        self.infos[msg["header"]["stamp_ns"]] = msg
        self.last_info = msg
        while len(self.infos) > self.max_frames:
            self.infos.popitem(last=False)

    def add_keypoints(self, msg: dict) -> None:
        stamp = msg["header"]["stamp_ns"]
        if stamp in self.frames:
            self.frames[stamp].keypoints = msg
        elif stamp > self.emitted_stamp:
            self.keypoints[stamp] = msg

    def add_pose(self, msg: dict, now: float) -> None:
        stamp = msg["header"]["stamp_ns"]
        self.last_pose_stamp = max(self.last_pose_stamp, stamp)
        self.last_pose_time = now
        if stamp in self.frames:
            self.frames[stamp].pose, self.frames[stamp].pose_arrived = msg, now
        elif stamp > self.emitted_stamp:
            self.poses[stamp] = (msg, now)

    # -- output ---------------------------------------------------------------------------
    def _ready(self, f: Frame, now: float) -> bool:
        return f.pose is not None and (f.keypoints is not None or now - f.pose_arrived >= self.grace_s)

    def _stalled(self, f: Frame, now: float) -> bool:
        """No pose for timeout_s while f waited."""
        last = self.last_pose_time if self.last_pose_time is not None else f.arrived
        return now - max(last, f.arrived) >= self.timeout_s

    def _expired(self, f: Frame, now: float) -> bool:
        return (f.pose is None and self.last_pose_stamp > f.stamp_ns) or self._stalled(f, now)

    def pop(self, now: float, flush: bool = False) -> list[Frame]:
        """Frames to draw now, oldest first (see the module docstring); flush: everything left."""
        out = []
        if self.keep_all:
            while self.frames:
                f = next(iter(self.frames.values()))
                full = len(self.frames) > self.max_frames
                if not (flush or full or self._ready(f, now) or self._expired(f, now)):
                    break
                self.overflowed += full and f.pose is None
                if f.pose is None and not full and self.last_paired is not None \
                        and f.stamp_ns - self.last_paired.stamp_ns <= self.hold_ns \
                        and self.last_pose_stamp > f.stamp_ns:   # skipped by the detector, not a stall
                    f.pose, f.keypoints, f.held = self.last_paired.pose, self.last_paired.keypoints, True
                out.append(self._take(f))
        else:
            ready = [f for f in self.frames.values() if self._ready(f, now)
                     or (f.pose is None and self._stalled(f, now))]
            if flush and not ready and self.frames:
                ready = [next(reversed(self.frames.values()))]
            if ready:
                newest = ready[-1]
                while self.frames:                         # drop everything older than it
                    f = self.frames.popitem(last=False)[1]
                    if f is newest:
                        break
                out.append(self._take(newest, popped=True))
            while len(self.frames) > self.max_frames:
                self.frames.popitem(last=False)
        self._forget_old()
        return out

    def _take(self, f: Frame, popped: bool = False) -> Frame:
        if not popped:
            del self.frames[f.stamp_ns]
        self.emitted_stamp = max(self.emitted_stamp, f.stamp_ns)
        if f.pose is not None and not f.held:
            self.last_paired = f
        f.info = self.infos.get(f.stamp_ns) or self._info_before(f.stamp_ns)
        return f

    def _info_before(self, stamp: int) -> dict | None:
        before = [s for s in self.infos if s <= stamp]
        return self.infos[max(before)] if before else self.last_info

    def _forget_old(self) -> None:
        """Poses, keypoints and infos of frames already drawn (or dropped), or of images that
        will not come (an image older than one already in: one publisher's images arrive in
        order; a latest-only subscription dropped it), can go; at most max_frames are kept."""
        floor = min(self.frames) if self.frames else self.emitted_stamp + 1
        for d in (self.poses, self.keypoints):
            for s in sorted(d)[:-self.max_frames] + [s for s in d if s < floor]:
                d.pop(s, None)
        keep_from = max((s for s in self.infos if s <= floor), default=None)
        for s in [s for s in self.infos if keep_from is not None and s < keep_from]:
            del self.infos[s]
