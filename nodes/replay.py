"""replay: a camera from a recording. Publishes /camera/image and /camera/info.

Source: a video file, a folder of images (subfolders included, sorted by path) or an MCAP bag (its /camera/image
messages; their stamps are replaced by the replay time, as a camera would stamp them).
`rate` is a speed factor over the source's frame rate (1 = real time, 0 = as fast as the
graph takes them: the next frame is decoded once fewer than AHEAD sent frames are still
queued for or held by a subscriber); `start` skips that many seconds; `loop` restarts at the end; `duration` (seconds, null: no
limit) ends the stream after that long (with `loop`: a long run). A replay respawned by its launcher
continues after the frames it had sent (Progress), with their sequence numbers. /camera/info
comes from `calibration` (a file, see handmocap.perception.camera_info) or, failing that, from the
bag's own /camera/info, or from a default field of view (camera_info.DEFAULT_HFOV_DEG) that
the message marks with source "default-fov". It is sent with every frame, so late subscribers
get it at once (a latched topic by repetition). `jpeg_quality` (1-100) publishes JPEG images
instead of raw bgr8 (null), as a network camera would.

`stamps`: "capture" (default) stamps each frame with the time it is published, as a camera
does; "source" with the source's own timeline (frame i at i / fps, a bag's frames at their
recorded times), placed so that the last frame's stamp is the first one's publish time: at
rate 0 the graph runs faster than the clip, and a bag recorded by stamp (the recorder's
`log_time: stamp`) then plays back at the clip's speed, not the processing's. Not with `loop`.
"auto": "source" at rate 0 without loop, else "capture" (launch/replay.yaml).
"""
from __future__ import annotations

import os
import time
from collections import deque
from pathlib import Path

from handmocap.perception import camera_info
from handmocap.runtime import codec
from handmocap.runtime.frames import frame_bgr, image_message, open_frames
from handmocap.runtime.node import Node, check_bool_param, check_jpeg_param, check_number_param, run

JIT_MARGIN_S = 0.002   # decode the next frame this long plus twice its recent decoding time before it is due
AHEAD = 3   # at rate 0, frames sent and not yet taken by every subscriber before the next is decoded

PARAMS = {"source": None, "rate": 1.0, "fps": None, "start": 0.0, "loop": False,
          "calibration": None, "frame_id": "camera", "jpeg_quality": None,
          "duration": None, "stamps": "capture"}
STAMPS = ("capture", "source", "auto")


def check_params(params: dict) -> None:
    """The launcher's check before any process starts (ValueError naming the param): a source
    that exists, numbers that are numbers, a calibration file that reads (so a mistyped input
    starts nothing, and the recorder's earlier bag stays as it was)."""
    source = params.get("source")
    if params.get("stamps", PARAMS["stamps"]) not in STAMPS:
        raise ValueError(f"replay param stamps: expected capture, source or auto, got {params.get('stamps')!r}")
    if params.get("stamps") == "source" and params.get("loop"):
        raise ValueError("replay param stamps: source stamps a clip's own timeline once; not with loop:=true")
    if not source:
        raise ValueError("replay param source: none given; a video file, an image folder or a .mcap bag")
    if not Path(str(source)).expanduser().exists():
        raise ValueError(f"replay param source: no such file or folder {source}")
    check_number_param("replay", "rate", params.get("rate", PARAMS["rate"]), minimum=0)
    check_number_param("replay", "fps", params.get("fps"), positive=True, null=True)
    check_number_param("replay", "start", params.get("start", PARAMS["start"]), minimum=0)
    check_bool_param("replay", "loop", params.get("loop", PARAMS["loop"]))
    check_number_param("replay", "duration", params.get("duration"), positive=True, null=True)
    check_jpeg_param("replay", params.get("jpeg_quality"))
    camera_info.check_calibration_param("replay", params.get("calibration"))


def source_span_s(source: Path, frames, start_s: float) -> float:
    """Seconds from the first frame replayed to the last: a video's or folder's frame count over
    its fps (`frames`), a bag's /camera/image log time span (frames None)."""
    if frames is None:
        from handmocap.runtime.bag import iter_messages
        times = [ns for _, t, _, ns in iter_messages(source) if t == "Image"]
        return max((times[-1] - times[0]) / 1e9 - start_s, 0.0) if times else 0.0
    return max(frames.frame_count - 1 - frames.start_frame, 0) / frames.fps


def bag_frames(path: Path, start_s: float, skip: int = 0):
    """(frame BGR, CameraInfo body or None) for each /camera/image of a bag (the first `skip`
    images after `start_s` left out)."""
    from handmocap.runtime.bag import iter_messages
    info, t0 = None, None
    for topic, type_name, payload, log_ns in iter_messages(path):
        if type_name == "CameraInfo":
            m = codec.decode(payload, type_name)
            info = {k: v for k, v in m.items() if k != "header"}
        elif type_name == "Image":
            t0 = log_ns if t0 is None else t0
            if (log_ns - t0) / 1e9 < start_s:
                continue
            if skip > 0:
                skip -= 1
                continue
            yield log_ns, frame_bgr(codec.decode(payload, type_name)), info


class Progress:
    """How many frames this replay has sent in this launch, in <run dir>/<node>.progress, so a
    respawned replay continues where the killed one stopped (same frames, same sequence
    numbers) instead of sending the recording again from its start. A new launch (another
    HANDMOCAP_LAUNCH_ID) starts afresh; so does a replay outside handlaunch."""

    def __init__(self, node: Node):
        self.launch = os.environ.get("HANDMOCAP_LAUNCH_ID")
        self.path = node.dir / f"{node.name}.progress"
        self.file = None

    def resume(self) -> int:
        """Frames sent by an earlier process of this launch (0: none)."""
        try:
            launch, sent = self.path.read_text().split()
            return int(sent) if self.launch and launch == self.launch else 0
        except (OSError, ValueError):
            return 0

    def sent(self, n: int) -> None:
        if self.launch is None:
            return
        if self.file is None:
            self.file = open(self.path, "w")
        self.file.seek(0)
        self.file.write(f"{self.launch} {n:>12d}\n")   # fixed width: no stale tail after a shorter number
        self.file.flush()                               # to the OS: survives this process being killed


def for_frames(calib, w: int, h: int, path) -> camera_info.Intrinsics:
    """Intrinsics for w x h frames: the calibration scaled to them (an error names its file),
    else the default field of view."""
    if calib is None:
        return camera_info.default_intrinsics(w, h)
    try:
        return calib.for_size(w, h)
    except ValueError as e:
        raise ValueError(f"calibration file {path}: {e}") from None


def main() -> None:
    node = Node("replay", params=PARAMS)
    # closed on every way out: a source that fails mid-stream (a video corrupt halfway) must
    # still flush and release its zero-copy frames, or libzmq aborts the process at exit
    # ("Bad address (src/tcp.cpp:227)", SIGABRT) after the one error line
    try:
        replay(node)
    finally:
        node.close()


def replay(node: Node) -> None:
    p = node.params
    if not p["source"]:
        raise ValueError("replay needs a source: a video file, an image folder or a .mcap bag (source:=PATH)")
    source = Path(p["source"]).expanduser()
    node.advertise("/camera/image", "Image")
    node.advertise("/camera/info", "CameraInfo")
    calib = camera_info.load_calibration(p["calibration"]) if p["calibration"] else None
    rate = float(p["rate"])
    is_bag = source.suffix == ".mcap"
    by_source = p["stamps"] == "source" or (p["stamps"] == "auto" and rate == 0 and not p["loop"])
    progress = Progress(node)
    resume = 0 if p["loop"] else progress.resume()   # a looping replay starts its loop afresh
    if resume:
        node.log.warning("respawned: continuing after the %d frame(s) sent before", resume)
        node.seq["/camera/image"] = node.seq["/camera/info"] = resume   # sequence numbers go on too
    if not is_bag:
        frames = open_frames(source, p["fps"], float(p["start"]))   # fails now on a bad source
        frames.start_frame += resume
    if "HANDMOCAP_LAUNCH_ID" in os.environ:
        # wait for the graph here rather than in the first publish: the first stamp and the
        # pacing clock then start when every node is up (else frame 0's latency counts the
        # graph's start-up, and the frames due meanwhile go out in one burst that queues)
        node.wait_for_graph()
    sent = 0
    end_at = time.monotonic() + float(p["duration"]) if p["duration"] is not None else None
    own_info = {"width": None, "height": None}   # the CameraInfo body of our frame size (publish copies it)
    while node.ok():
        if is_bag:
            seq = ((ns / 1e9, f, info) for ns, f, info in bag_frames(source, float(p["start"]), resume))
        else:
            seq = ((i / frames.fps, f, None) for i, f in frames)
        t_first = t_start = None   # source time and clock of this pass's first frame
        decode_s = deque(maxlen=30)   # the last frames' decoding times, s
        frames_in = iter(seq)
        t_next = None   # source time of the next frame where it is known before decoding (video, folder)
        while node.ok():
            if rate > 0 and t_first is not None and t_next is not None:
                # decode just before the frame is due, not right after the last one went out:
                # a camera's frame does not cost the graph CPU while the previous one is still
                # being processed (with the source in the perception container, decoding
                # alongside the detector also costs it GIL hand-offs: +0.8 ms p50 measured)
                lead = min(2 * max(decode_s, default=0.0) + JIT_MARGIN_S, 0.5 / (rate * frames.fps))
                early = t_start + (t_next - t_first) / rate - lead - time.monotonic()
                if early > 0:
                    time.sleep(early)
            elif rate == 0:   # as fast as the graph takes frames, not as fast as they decode
                node.wait_in_flight(AHEAD)
            t0 = time.monotonic()
            item = next(frames_in, None) if end_at is None or t0 < end_at else None
            if item is None:
                break
            t_src, frame, bag_info = item
            if t_first is None:   # the clock starts with the first frame in hand
                t_first, t_start = t_src, time.monotonic()
            else:
                decode_s.append(time.monotonic() - t0)
            if not is_bag:
                t_next = t_src + 1 / frames.fps
            if rate > 0:
                delay = t_start + (t_src - t_first) / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            h, w = frame.shape[:2]
            if calib is None and bag_info is not None:
                info = bag_info
            else:
                if (own_info["width"], own_info["height"]) != (w, h):   # computed once per frame size
                    intr = for_frames(calib, w, h, p["calibration"])
                    own_info = camera_info.camera_info_message(intr.K, intr.distortion, w, h, intr.source)
                info = own_info
            stamp = time.time_ns()
            if by_source:       # the clip's timeline, ending at the first frame's publish time
                if sent == 0:
                    origin = stamp - int(1e9 * (source_span_s(source, None if is_bag else frames, float(p["start"]))))
                stamp = origin + int(1e9 * (t_src - t_first))
            # the info first, as the camera nodes send it: a frame's subscribers have its K when
            # the frame comes, and nothing delays their turn after it (in the perception
            # container, the detector waited for the info's publish: +0.25 ms p50 measured)
            node.publish("/camera/info", info, stamp_ns=stamp, frame_id=p["frame_id"])
            node.publish("/camera/image", image_message(frame, p["jpeg_quality"]), stamp_ns=stamp, frame_id=p["frame_id"])
            sent += 1
            progress.sent(resume + sent)
        if not p["loop"] or t_first is None or (end_at is not None and time.monotonic() >= end_at):
            break
    node.log.info("replayed %d frame(s) from %s", sent, source)


if __name__ == "__main__":
    run(main)
