"""`name:=value` command-line params, as handlaunch and every node read them (ROS 2's `--ros-args -p`).

Kept apart from node.py so that the launcher, which reads them too, does not import the
codec (numpy): a supervisor that only starts and watches processes stays small
(benchmarks/bench_memory.py)."""
from __future__ import annotations

import yaml


def parse_cli_params(argv: list[str]) -> dict:
    """`name:=value` pairs, values parsed as YAML scalars (so 2 is an int, true a bool)."""
    out = {}
    for arg in argv:
        if ":=" not in arg:
            raise ValueError(f"expected name:=value, got {arg!r}")
        k, v = arg.split(":=", 1)
        if k in out:   # the last would silently win
            raise ValueError(f"{k} is given twice: {k}:={out[k]!r} and {arg!r}")
        out[k] = yaml.safe_load(v) if v else ""
    return out
