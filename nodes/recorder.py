"""recorder: writes topics of the graph to an MCAP bag, payloads as received (images compressed).

Params: `output` (bag path; parent folders are made; an existing file is an error unless
`overwrite` is true; the file is written, or an earlier one replaced, only when the first
message arrives: a graph that fails before sending anything leaves no empty bag and the
earlier recording as it was), `topics` (list; empty =
every topic of the graph), `raw` and `jpeg_quality`: images (Image messages in bgr8, rgb8 or
mono8) are stored as JPEG of that quality (benchmarks/bench_recording.py measures the size),
unless `raw` is true or jpeg_quality null (lossless, byte for byte). Subscriptions are
keep-all. Each message is stored with its receive time as MCAP log time and its header
stamp as publish time. The bag is finished properly (summary, footer) on SIGINT/SIGTERM and
when every recorded input has ended; a one-line summary is logged at the end.

Splits, as rosbag2's: with `split_s` (seconds of recording) or `split_mb` (MB) the bag is a
series take_0000.mcap, take_0001.mcap, ... (names in order; `output` take.mcap names them),
each closed whole before the next opens: a crash costs only the open split's last chunk.
With `overwrite`, splits of an earlier recording under that name are removed when the first
message arrives.
"""
from __future__ import annotations

from pathlib import Path

from handmocap.runtime import codec
from handmocap.runtime.bag import BagWriter, SplitBagWriter, bag_info, split_paths
from handmocap.runtime.frames import compressed
from handmocap.runtime.node import Node, check_bool_param, check_jpeg_param, check_number_param, run

PARAMS = {"output": "out.mcap", "topics": [], "overwrite": False, "raw": False, "jpeg_quality": 90,
          "split_s": None, "split_mb": None}
IDLE_TICK_S = 0.5   # when nothing arrives this long, close the open chunk if it is old


def output_path(output: str, overwrite: bool, split: bool = False) -> Path:
    """The bag path `output`; FileExistsError names the file if it exists and may not be replaced
    (with `split`: its first split)."""
    path = Path(output).expanduser()
    if split and split_paths(path) and not overwrite:
        raise FileExistsError(f"{split_paths(path)[0]} already exists (remove the splits of {path}, choose "
                              f"another output, or set overwrite:=true)")
    if path.exists() and not overwrite and not split:
        cut = ""
        try:
            if bag_info(path)["truncated"]:
                cut = f"; it was cut short (its recorder was killed): `handbag repair {path}` makes it whole"
        except (OSError, ValueError):
            pass
        raise FileExistsError(f"{path} already exists (remove it, choose another "
                              f"output, or set overwrite:=true){cut}")
    return path


def is_split(params: dict) -> bool:
    """Whether the recorder's params ask for a split recording (`split_s` or `split_mb`)."""
    return params.get("split_s") is not None or params.get("split_mb") is not None


def open_output(output: str, overwrite: bool, split_s=None, split_mb=None):
    """A BagWriter on `output` (parent folders made), or a SplitBagWriter with `split_s` or
    `split_mb` (an earlier recording's splits under that name removed); FileExistsError as output_path."""
    split = split_s is not None or split_mb is not None
    path = output_path(output, overwrite, split)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not split:
        return BagWriter(path)
    for old in split_paths(path):
        old.unlink()
    return SplitBagWriter(path, split_s, None if split_mb is None else int(split_mb * 1e6))


def check_params(params: dict) -> None:
    """The launcher's check before any process starts: an existing output that may not be
    replaced, or an overwrite that is no bool, is one error (nothing else has started)."""
    overwrite = params.get("overwrite", PARAMS["overwrite"])
    check_bool_param("recorder", "overwrite", overwrite)
    check_bool_param("recorder", "raw", params.get("raw", PARAMS["raw"]))
    check_jpeg_param("recorder", params.get("jpeg_quality", PARAMS["jpeg_quality"]))
    for key in ("split_s", "split_mb"):
        check_number_param("recorder", key, params.get(key), positive=True, null=True)
    split = is_split(params)
    try:
        output_path(str(params.get("output", PARAMS["output"])), overwrite, split)
    except FileExistsError as e:
        raise ValueError(f"recorder param output: {e}") from None


def summary_line(counts: dict, path: Path) -> str:
    """'recorded 12 message(s) to out.mcap: /a 10, /b 2'."""
    total = sum(counts.values())
    per_topic = ", ".join(f"{t} {n}" for t, n in sorted(counts.items())) or "no topics"
    return f"recorded {total} message(s) to {path}: {per_topic}"


def main(argv: list[str] | None = None, name: str = "recorder") -> None:
    """Run the recorder; `argv` (name:=value params) defaults to sys.argv[1:]."""
    node = Node(name, params=PARAMS, argv=argv)
    p = node.params
    topics = p["topics"]
    if isinstance(topics, str):
        topics = [topics]
    try:
        split = is_split(p)
        path = output_path(str(p["output"]), bool(p["overwrite"]), split)
        # the bag is made (or an earlier one replaced) by the first message, not at start: a
        # graph that fails at once must leave neither an empty bag nor a replaced recording
        bag = None
    except Exception:
        node.close()
        raise
    try:
        if topics:
            for topic in topics:
                node.subscribe(topic, None, mode="lossless")   # a bag is complete: publishers wait for it
        else:
            node.subscribe(None, None, mode="lossless")
        node.log.info("recording %s to %s%s", ", ".join(topics) or "every topic",
                      f"splits of {path}" if split else path,
                      " (replacing it once the first message arrives)" if path.exists() or
                      (split and split_paths(path)) else "")
        refused: set[str] = set()   # topics seen with a second message type (a graph bug)
        for msg in node.events(timeout=IDLE_TICK_S):
            if msg is None:
                if bag is not None:
                    bag.tick()
                continue
            if bag is None:
                bag = open_output(str(path), True, p["split_s"], p["split_mb"])
            payload = msg.raw
            if msg.type == "Image" and not p["raw"] and p["jpeg_quality"] and msg.data["encoding"] != "jpeg":
                payload = codec.encode(compressed(msg.data, int(p["jpeg_quality"])), "Image")
            try:
                bag.write(msg.topic, msg.type, payload, msg.recv_ns, msg.stamp_ns)
            except ValueError as e:   # one channel holds one type: keep the first, skip the rest
                if msg.topic not in refused:
                    refused.add(msg.topic)
                    node.log.warning("not recording some messages: %s", e)
    finally:
        if bag is None:
            node.log.info("recorded nothing: %s", f"{path} left as it was" if path.exists() else f"no {path} written")
        else:
            bag.close()
            where = bag.path if not isinstance(bag, SplitBagWriter) else \
                f"{bag.paths[0]} ... {bag.paths[-1].name} ({len(bag.paths)} splits)"
            node.log.info("%s", summary_line(bag.counts, where))
        node.close()


if __name__ == "__main__":
    run(main)
