"""`handbag`: record, play, inspect and export MCAP bags of the graph (like `ros2 bag`).

  handbag record -o OUT.mcap [TOPIC ...] [--overwrite]   until Ctrl-C or the graph ends
  handbag play FILE [--rate R] [--loop] [--topics T ...] payloads as recorded, paced by log time
  handbag info FILE [--json]                             topics, counts, time span, truncated?
  handbag export FILE -o OUT.mcap --foxglove             a copy Foxglove Studio decodes

The graph is the one of the current run dir (`bus.run_dir()`: $HANDMOCAP_RUN_DIR, or
$HANDMOCAP_GRAPH / "default"). Errors are one line, `handbag: error: ...`, exit status 1.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from pathlib import Path

from handmocap.runtime.bag import NotABag, bag_info, checked_info, is_split, play_messages, playable_topics, record

SUBSCRIBER_WAIT_S = 5.0   # how long play waits for the graph's subscribers to connect


class CliError(Exception):
    """An expected failure, reported as one `handbag: error:` line."""


# -- record ----------------------------------------------------------------------------------
def cmd_record(args) -> None:
    from handmocap.runtime.node import Node
    out = Path(args.output).expanduser()
    if out.exists() and not args.overwrite and not is_split(args.split_s, args.split_mb):
        raise CliError(f"{out} already exists (remove it, choose another -o, or pass --overwrite)")
    node = Node(f"bagrec{os.getpid()}", argv=[])
    try:
        record(node, str(args.output), args.topics or [], args.overwrite, split_s=args.split_s, split_mb=args.split_mb)
    finally:
        node.close()


# -- play ------------------------------------------------------------------------------------
def cmd_play(args) -> None:
    from handmocap.runtime.node import Node
    topics = playable_topics(args.file, args.topics)
    node = Node(f"bagplay{os.getpid()}", argv=[])
    try:
        for topic, type_name in topics.items():
            node.advertise(topic, type_name)
        if "HANDMOCAP_LAUNCH_ID" not in os.environ:
            missing = node.wait_for_subscribers(SUBSCRIBER_WAIT_S)
            if missing:
                node.log.warning("playing without all subscribers connected: %s", missing)
        sent = play_messages(node, args.file, topics, args.rate, args.loop)
        node.log.info("played %d message(s) from %s", sent, args.file)
    finally:
        node.close()


# -- info ------------------------------------------------------------------------------------
def _fmt_time(ns: int | None) -> str:
    if ns is None:
        return "-"
    return datetime.datetime.fromtimestamp(ns / 1e9).isoformat(sep=" ", timespec="milliseconds")


def _fmt_bytes(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"


def format_info(info: dict) -> str:
    """The human-readable `handbag info` table."""
    trunc = (f"yes: the writer did not finish; {info['unreadable_bytes']} byte(s) at the end unreadable; "
             f"`handbag repair {info['path']}` makes it whole for any MCAP reader"
             if info["truncated"] else "no")
    lines = [f"path:       {info['path']}",
             f"size:       {_fmt_bytes(info['size_bytes'])}",
             f"messages:   {info['message_count']}",
             f"start:      {_fmt_time(info['start_ns'])}",
             f"end:        {_fmt_time(info['end_ns'])}",
             f"duration:   {info['duration_s']:.3f} s",
             f"truncated:  {trunc}"]
    if info["topics"]:
        rows = [("topic", "type", "count", "encoding")]
        rows += [(topic, v["type"], str(v["count"]), v["encoding"]) for topic, v in info["topics"].items()]
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines.append("")
        lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    return "\n".join(lines)


def cmd_info(args) -> None:
    info = bag_info(args.file)
    print(json.dumps(info, indent=2) if args.json else format_info(info))


def cmd_repair(args) -> None:
    from handmocap.runtime.bag import repair
    result = repair(args.file)
    if not result["repaired"]:
        print(f"{args.file}: whole already ({result['message_count']} messages); nothing to do")
        return
    print(f"{args.file}: repaired: {result['message_count']} messages kept, any MCAP reader opens it now "
          f"({result['dropped_bytes']} bytes of a record cut short dropped)")


# -- export ----------------------------------------------------------------------------------
def cmd_export(args) -> None:
    if args.ros2:
        return export_ros2_cli(args)
    from handmocap.interop.foxglove_export import export_foxglove
    if not args.foxglove:
        raise CliError("export needs a target format: --foxglove -o OUT.mcap, or --ros2 OUT_FOLDER")
    if not args.output:
        raise CliError("export --foxglove needs -o OUT.mcap")
    src, dst = Path(args.file), Path(args.output)
    checked_info(args.file, args.topics)
    if dst.exists() and dst.resolve() == src.resolve():
        raise CliError(f"{dst}: the output would overwrite the input bag")
    dst.parent.mkdir(parents=True, exist_ok=True)
    result = export_foxglove(src, dst, args.topics)
    for topic, v in result["topics"].items():
        print(f"{topic}: {v['count']} message(s) as {v['schema']}")
    for topic, n in result["skipped"].items():
        print(f"{topic}: skipped {n} malformed message(s)", file=sys.stderr)
    print(f"wrote {dst}")


def export_ros2_cli(args) -> None:
    from handmocap.interop.ros2_export import export_ros2
    src, dst = Path(args.file), Path(args.ros2)
    checked_info(args.file, args.topics)
    if dst.exists():
        raise CliError(f"{dst} already exists: a rosbag2 is a new folder (remove it or choose another)")
    result = export_ros2(src, dst, args.topics)
    for topic, (msgtype, n) in sorted(result["topics"].items()):
        print(f"{topic}: {n} message(s) as {msgtype}")
    for topic, why in result["skipped"].items():
        print(f"{topic}: not exported ({why})", file=sys.stderr)
    print(f"wrote {dst} (play it with: ros2 bag play {dst})")


# -- entry point -----------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="handbag", description="Record, play, inspect and export MCAP bags.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("record", help="record topics of the running graph until Ctrl-C or its end")
    r.add_argument("-o", "--output", required=True, help="bag file to write (.mcap)")
    r.add_argument("topics", nargs="*", help="topics to record (default: every topic)")
    r.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    r.add_argument("--split-s", type=float, default=None, metavar="S",
                   help="a new file every S seconds: OUT_0000.mcap, OUT_0001.mcap, ... (each whole once closed)")
    r.add_argument("--split-mb", type=float, default=None, metavar="MB", help="a new file every MB megabytes")
    r.set_defaults(func=cmd_record)

    pl = sub.add_parser("play", help="publish a bag's messages unchanged, paced by their log times")
    pl.add_argument("file")
    pl.add_argument("--rate", type=float, default=1.0, help="speed factor; 0 = as fast as possible")
    pl.add_argument("--loop", action="store_true", help="start over at the end, until Ctrl-C")
    pl.add_argument("--topics", nargs="+", help="play only these topics")
    pl.set_defaults(func=cmd_play)

    i = sub.add_parser("info", help="topics, message counts, time span, truncation")
    i.add_argument("file")
    i.add_argument("--json", action="store_true", help="machine-readable output")
    i.set_defaults(func=cmd_info)

    rp = sub.add_parser("repair", help="make a bag whose recorder was killed whole, in place (lossless)")
    rp.add_argument("file")
    rp.set_defaults(func=cmd_repair)

    e = sub.add_parser("export", help="write a copy in another encoding: Foxglove JSON or a ROS 2 bag")
    e.add_argument("file")
    e.add_argument("-o", "--output", help="file to write (.mcap), with --foxglove")
    e.add_argument("--foxglove", action="store_true",
                   help="JSON messages with Foxglove well-known schemas (images as JPEG)")
    e.add_argument("--ros2", metavar="OUT",
                   help="write a rosbag2 folder OUT (MCAP storage, CDR: sensor_msgs, geometry_msgs, tf2_msgs) "
                        "for ros2 bag play; needs the ros2 extra")
    e.add_argument("--topics", nargs="+", help="export only these topics")
    e.set_defaults(func=cmd_export)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except KeyboardInterrupt:
        pass
    except BrokenPipeError:                 # `handbag info X | head`: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())    # no second error at exit's flush
        return 0
    except (CliError, NotABag, FileNotFoundError, FileExistsError, ValueError, OSError, RuntimeError) as e:
        print(f"handbag: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
