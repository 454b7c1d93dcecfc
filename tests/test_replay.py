"""launch/replay.yaml end to end: a clip or a folder in, a bag with exactly its frames (and one
keypoints, shape and pose message per frame) out."""
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import ROOT, graph_env, handlaunch, write_test_video


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 90-frame 320x240 video of a moving red disc (no hand) and the same frames as a folder of PNGs."""
    d = tmp_path_factory.mktemp("clip")
    write_test_video(d / "clip.mp4", 90, fourcc="mp4v", background=40, folder=d / "frames",
                     draw=lambda i, img: cv2.circle(img, (20 + 3 * i, 120), 25, (0, 0, 255), -1))
    return d


def bag_counts(bag):
    r = subprocess.run([sys.executable, "-m", "handmocap.interop.bag_cli", "info", str(bag), "--json"],
                       capture_output=True, text=True, check=True)
    info = json.loads(r.stdout)
    return {t: v["count"] for t, v in info["topics"].items()}, info


@pytest.mark.parametrize("source", ["clip.mp4", "frames"])
def test_replay_into_recorder_records_every_frame(clip, tmp_path, run_dir, source):
    bag = tmp_path / "out.mcap"
    r = handlaunch([ROOT / "launch/replay.yaml", f"input:={clip / source}", f"bag:={bag}"], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    counts, info = bag_counts(bag)
    # every frame went through the whole chain (these frames show no hand: poses are empty)
    assert counts == {t: 90 for t in ("/camera/image", "/camera/info", "/hand/keypoints", "/hand/shape", "/hand/pose")}
    assert not info["truncated"]


def test_replay_with_calibration_file_publishes_its_K(clip, tmp_path, run_dir):
    calib = tmp_path / "calib.yaml"
    calib.write_text("K: [500.0, 500.0, 159.5, 119.5]\nwidth: 320\nheight: 240\n")
    bag = tmp_path / "out.mcap"
    r = handlaunch([ROOT / "launch/replay.yaml", f"input:={clip / 'clip.mp4'}", f"bag:={bag}",
                    f"calibration:={calib}"], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    from handmocap.runtime import codec
    from handmocap.runtime.bag import iter_messages
    infos = [codec.decode(p, t) for _, t, p, _ in iter_messages(bag, topics=["/camera/info"])]
    assert len(infos) == 90 and infos[0]["source"] == "calibration"
    np.testing.assert_allclose(infos[0]["K"], [[500, 0, 159.5], [0, 500, 119.5], [0, 0, 1]])


def test_jpeg_source_and_compressed_bag_replay_again(clip, tmp_path, run_dir):
    """jpeg:=90 makes the source publish JPEG frames (the detector decodes them); the bag, which
    stores images as JPEG by default, is a source itself: replaying it gives the same frames
    (nearly the same pixels) again."""
    from handmocap.runtime import codec
    from handmocap.runtime.bag import iter_messages
    from handmocap.runtime.frames import frame_bgr
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    r = handlaunch([ROOT / "launch/replay.yaml", f"input:={clip / 'frames'}", f"bag:={first}", "jpeg:=90"], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    r = handlaunch([ROOT / "launch/replay.yaml", f"input:={first}", f"bag:={second}"], run_dir)
    assert r.returncode == 0, r.stdout + r.stderr
    counts, _ = bag_counts(second)
    assert counts["/camera/image"] == counts["/hand/keypoints"] == 90
    originals = sorted((clip / "frames").iterdir())
    for bag in (first, second):
        images = [codec.decode(p, t) for _, t, p, _ in iter_messages(bag, topics=["/camera/image"])]
        assert len(images) == 90 and {m["encoding"] for m in images} == {"jpeg"}
        for m, path in list(zip(images, originals))[::15]:
            assert np.abs(frame_bgr(m).astype(int) - cv2.imread(str(path))).mean() < 4


@pytest.mark.parametrize("make, words", [
    (lambda d: d / "missing.mp4", "no such file or folder"),
    (lambda d: (d / "bad.mp4").write_bytes(b"\x00not a video" * 100) and d / "bad.mp4", "cannot be opened"),
    (lambda d: (d / "empty").mkdir() or d / "empty", "no images"),
])
def test_bad_source_is_one_clear_error(tmp_path, run_dir, make, words):
    src = make(tmp_path)
    r = subprocess.run([sys.executable, "-m", "handmocap.nodes.replay", f"source:={src}"],
                       env=graph_env(run_dir), capture_output=True, text=True, timeout=30)
    assert r.returncode == 2
    lines = [l for l in r.stderr.strip().splitlines() if l]
    assert len(lines) == 1 and words in lines[0] and str(src) in lines[0], r.stderr


def test_an_image_folder_includes_its_subfolders_sorted_by_path(tmp_path):
    """A dataset's per-person folders (`handeval predict --images DIR`, replay source:=DIR):
    every image below DIR, sorted by path; none at all is one error that says so."""
    import cv2
    import numpy as np

    from handmocap.runtime.frames import ImageFolderFrames
    for name in ("b/2.png", "a/1.jpg", "a/0.jpg", "top.png", "notes.txt"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        if name.endswith("txt"):
            (tmp_path / name).write_text("not an image")
        else:
            cv2.imwrite(str(tmp_path / name), np.full((8, 8, 3), len(name), np.uint8))
    frames = ImageFolderFrames(tmp_path)
    assert [p.relative_to(tmp_path).as_posix() for p in frames.files] == ["a/0.jpg", "a/1.jpg", "b/2.png", "top.png"]
    assert [i for i, _ in frames] == [0, 1, 2, 3]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no images .* subfolders included"):
        ImageFolderFrames(tmp_path / "empty")


def test_a_bag_recorded_at_rate_0_keeps_the_clips_timing(tmp_path, run_dir):
    """replay.yaml at rate 0 processes the demo clip faster than real time; its frames are
    stamped on the clip's own timeline (1/30 s apart, the last at the first's publish time) and
    the recorder logs by stamp, so the bag spans the clip's 89/30 s, and handbag play would
    take that long, not the processing time."""
    from handmocap.runtime import codec
    from handmocap.runtime.bag import bag_info, iter_messages
    bag = tmp_path / "r.mcap"
    r = handlaunch([ROOT / "launch/replay.yaml", f"input:={ROOT / 'data/demo/hand_clip.mp4'}", f"bag:={bag}"],
                   run_dir, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    info = bag_info(bag)
    assert abs((info["end_ns"] - info["start_ns"]) / 1e9 - 89 / 30) < 0.002, info
    stamps = np.array([codec.decode(p, t)["header"]["stamp_ns"] for _, t, p, _ in iter_messages(bag, ["/camera/image"])])
    assert len(stamps) == 90 and np.allclose(np.diff(stamps) / 1e9, 1 / 30, atol=1e-5)
    poses = [codec.decode(p, t)["header"]["stamp_ns"] for _, t, p, _ in iter_messages(bag, ["/hand/pose"])]
    assert sorted(poses) == sorted(stamps.tolist())          # each pose carries its frame's stamp


def test_source_stamps_refuse_a_loop():
    from handmocap.nodes import replay
    clip = str(ROOT / "data/demo/hand_clip.mp4")
    with pytest.raises(ValueError, match="stamps"):
        replay.check_params({"source": clip, "stamps": "source", "loop": True})
    with pytest.raises(ValueError, match="capture, source or auto"):
        replay.check_params({"source": clip, "stamps": "media"})
    replay.check_params({"source": clip, "stamps": "auto", "loop": True})
