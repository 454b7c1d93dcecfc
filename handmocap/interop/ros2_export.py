"""`handbag export --ros2 OUT`: a project bag as a ROS 2 bag (rosbag2: MCAP storage, CDR,
metadata.yaml) that `ros2 bag info` and `ros2 bag play` take, without a ROS install.

The topics and types are those of handmocap.interop.ros2_messages (the live `ros2` node
publishes the same messages); other topics are left out (listed by the export).
"""
from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

from handmocap.runtime import codec
from handmocap.runtime.bag import iter_messages
from handmocap.interop.ros2_messages import Ros2Messages, typestore


def export_ros2(src: Path, dst: Path, topics=None) -> dict:
    """Write the rosbag2 folder `dst` (must not exist) from the project bag `src`. Returns
    {"topics": {ros topic: (type, count)}, "skipped": {project topic: reason}}."""
    ts = typestore()
    partial = dst.with_name(dst.name + ".partial")     # renamed to dst once complete
    shutil.rmtree(partial, ignore_errors=True)
    try:
        result = _write(ts, src, partial, topics)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    # rosbag2 names the storage file after its folder: rename both
    (partial / f"{partial.name}.mcap").rename(partial / f"{dst.name}.mcap")
    meta = partial / "metadata.yaml"
    meta.write_text(meta.read_text().replace(f"{partial.name}.mcap", f"{dst.name}.mcap"))
    partial.rename(dst)
    return result


def _write(ts, src: Path, dst: Path, topics) -> dict:
    from rosbags.rosbag2 import StoragePlugin, Writer
    build = Ros2Messages(ts)
    counts, skipped = Counter(), {}
    types: dict[str, str] = {}
    with Writer(dst, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}

        def write(topic, msgtype, message, log_ns):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                types[topic] = msgtype
            writer.write(connections[topic], int(log_ns), ts.serialize_cdr(message, msgtype))
            counts[topic] += 1

        for topic, type_name, payload, log_ns in iter_messages(src, topics):
            try:
                msg = codec.decode(payload, type_name)
            except codec.MalformedMessage as e:
                skipped[topic] = f"malformed: {e}"
                continue
            converted = build.convert(type_name, msg)
            if converted is None:
                skipped.setdefault(topic, f"{type_name} has no ROS 2 counterpart here")
            for ros_topic, msgtype, message in converted or ():
                write(ros_topic, msgtype, message, log_ns)
    return {"topics": {t: (types[t], n) for t, n in counts.items()}, "skipped": skipped}
