"""The one codec of the wire: msgpack payloads, validated against `messages/*.json`.

A message is a plain dict. numpy arrays anywhere in it travel as
`{"dtype": str, "shape": [int], "data": bytes}` (C order, little-endian), never as
per-element lists; `decode` turns them back into read-only arrays that view the payload.
"""
from __future__ import annotations

import functools
import json
import math
import os
import time
from importlib import resources

import fastjsonschema
import msgpack
import numpy as np

# Larger payloads are dropped unread; a 4K BGR frame is 25 MB.
MAX_MESSAGE_BYTES = int(os.environ.get("HANDMOCAP_MAX_MESSAGE_BYTES", 64 * 1024 * 1024))
_ARRAY_KEYS = frozenset(("dtype", "shape", "data"))


class MalformedMessage(ValueError):
    """A payload that is not a valid message of its type; `reason` is a short slug for counters."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


def message_types() -> list[str]:
    """Names of all message types, from the schema files in `messages/`."""
    return sorted(p.name[:-5] for p in resources.files("handmocap.messages").iterdir()
                  if p.name.endswith(".json") and p.name != "common.json")


@functools.cache
def schema(type_name: str) -> dict:
    """The JSON Schema of one message type, with the shared `$defs` merged in."""
    pkg = resources.files("handmocap.messages")
    path = pkg / f"{type_name}.json"
    if not type_name.isidentifier() or not path.is_file():
        raise KeyError(f"unknown message type {type_name!r} (known: {', '.join(message_types())})")
    s = json.loads(path.read_text())
    s["$defs"] = {**json.loads((pkg / "common.json").read_text())["$defs"], **s.get("$defs", {})}
    return s


@functools.cache
def _validator(type_name: str):
    return fastjsonschema.compile(schema(type_name))


_DTYPE_NAMES = {np.dtype(n): n for n in  # dtype.name is slow: a lookup table for the wire types
                ("uint8", "uint16", "int8", "int16", "int32", "int64", "float16", "float32", "float64", "bool")}
_SMALL_ARRAY_BYTES = 4096  # below this a copy (tobytes) is cheaper than a memoryview cast


def _to_wire(obj):
    if isinstance(obj, np.ndarray):
        a = obj if obj.flags.c_contiguous else np.ascontiguousarray(obj)
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        data = a.tobytes() if a.nbytes <= _SMALL_ARRAY_BYTES else memoryview(a).cast("B")
        return {"dtype": _DTYPE_NAMES.get(a.dtype) or a.dtype.name, "shape": list(a.shape), "data": data}
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def encode(msg: dict, type_name: str | None = None) -> bytes:
    """Pack one message; with `type_name`, validate it first (raises MalformedMessage)."""
    payload = msgpack.packb(msg, default=_to_wire, use_bin_type=True)
    if type_name is not None:
        decode(payload, type_name)
    return payload


_DTYPES = {name: dt for dt, name in _DTYPE_NAMES.items()}


def _arrays_from_wire(obj):
    """Replace every {dtype, shape, data} map (already schema-checked) by a numpy view, in place."""
    items = obj.items() if isinstance(obj, dict) else enumerate(obj)
    for k, v in items:
        if isinstance(v, dict):
            if len(v) == 3 and "data" in v and "dtype" in v and "shape" in v:
                obj[k] = _array(v)
            else:
                _arrays_from_wire(v)
        elif isinstance(v, list) and v and isinstance(v[0], (dict, list)):
            _arrays_from_wire(v)
    return obj


def _array(v: dict) -> np.ndarray:
    dt, shape, data = _DTYPES[v["dtype"]], v["shape"], v["data"]
    if not isinstance(data, bytes) or len(data) != math.prod(shape) * dt.itemsize:
        raise MalformedMessage("array-size", f"{v['dtype']}{shape} needs {math.prod(shape) * dt.itemsize}"
                               f" bytes, got {len(data) if isinstance(data, bytes) else type(data).__name__}")
    return np.frombuffer(data, dtype=dt).reshape(shape)


def decode(payload: bytes, type_name: str, max_bytes: int = MAX_MESSAGE_BYTES) -> dict:
    """Unpack and validate one payload of type `type_name`; arrays come back as numpy views.

    Raises MalformedMessage (reason: oversized, msgpack, schema, array-size, unknown-type).
    """
    if len(payload) > max_bytes:
        raise MalformedMessage("oversized", f"{len(payload)} bytes > limit {max_bytes}")
    try:
        validate = _validator(type_name)
    except KeyError as e:
        raise MalformedMessage("unknown-type", str(e)) from None
    try:
        raw = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises a zoo of types on garbage
        raise MalformedMessage("msgpack", f"{type(e).__name__}: {e}") from None
    try:
        validate(raw)
    except fastjsonschema.JsonSchemaException as e:
        raise MalformedMessage("schema", e.message) from None
    return _arrays_from_wire(raw)


def header(seq: int, frame_id: str = "camera", stamp_ns: int | None = None) -> dict:
    """The header every message starts with (DESIGN.md): capture stamp, sequence, frame id."""
    return {"stamp_ns": time.time_ns() if stamp_ns is None else int(stamp_ns), "seq": int(seq),
            "frame_id": frame_id}
