"""recorder: writes topics of the graph to an MCAP bag, payloads as received (images compressed).

Params: `output` (bag path; parent folders are made; an existing file is an error unless
`overwrite` is true; the file is written, or an earlier one replaced, only when the first
message arrives: a graph that fails before sending anything leaves no empty bag and the
earlier recording as it was), `topics` (list; empty =
every topic of the graph), `raw` and `jpeg_quality`: images (Image messages in bgr8, rgb8 or
mono8) are stored as JPEG of that quality (benchmarks/bench_recording.py measures the size),
unless `raw` is true or jpeg_quality null (lossless, byte for byte). Subscriptions are
keep-all. Each message is stored with its receive time as MCAP log time (`log_time: stamp`:
its header stamp, for a replay on the source's timeline) and its header stamp as publish time. The bag is finished properly (summary, footer) on SIGINT/SIGTERM and
when every recorded input has ended; a one-line summary is logged at the end.

Splits, as rosbag2's: with `split_s` (seconds of recording) or `split_mb` (MB) the bag is a
series take_0000.mcap, take_0001.mcap, ... (names in order; `output` take.mcap names them),
each closed whole before the next opens: a crash costs only the open split's last chunk.
With `overwrite`, splits of an earlier recording under that name are removed when the first
message arrives.
"""
from __future__ import annotations

from handmocap.runtime.bag import is_split, output_path, record
from handmocap.runtime.node import Node, check_bool_param, check_jpeg_param, check_number_param, run

PARAMS = {"output": "out.mcap", "topics": [], "overwrite": False, "raw": False, "jpeg_quality": 90,
          "split_s": None, "split_mb": None, "log_time": "receipt"}


def check_params(params: dict) -> None:
    """The launcher's check before any process starts: an existing output that may not be
    replaced, or an overwrite that is no bool, is one error (nothing else has started)."""
    overwrite = params.get("overwrite", PARAMS["overwrite"])
    check_bool_param("recorder", "overwrite", overwrite)
    check_bool_param("recorder", "raw", params.get("raw", PARAMS["raw"]))
    check_jpeg_param("recorder", params.get("jpeg_quality", PARAMS["jpeg_quality"]))
    if params.get("log_time", PARAMS["log_time"]) not in ("receipt", "stamp"):
        raise ValueError(f"recorder param log_time: expected receipt or stamp, got {params.get('log_time')!r}")
    for key in ("split_s", "split_mb"):
        check_number_param("recorder", key, params.get(key), positive=True, null=True)
    split = is_split(params.get("split_s"), params.get("split_mb"))
    try:
        output_path(str(params.get("output", PARAMS["output"])), overwrite, split)
    except FileExistsError as e:
        raise ValueError(f"recorder param output: {e}") from None


def main(argv: list[str] | None = None, name: str = "recorder") -> None:
    """Run the recorder; `argv` (name:=value params) defaults to sys.argv[1:]."""
    node = Node(name, params=PARAMS, argv=argv)
    p = node.params
    try:
        record(node, str(p["output"]), [p["topics"]] if isinstance(p["topics"], str) else list(p["topics"]),
               bool(p["overwrite"]), bool(p["raw"]), p["jpeg_quality"], p["split_s"], p["split_mb"], p["log_time"])
    finally:
        node.close()


if __name__ == "__main__":
    run(main)
