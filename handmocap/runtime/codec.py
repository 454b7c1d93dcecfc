"""The one codec of the wire: msgpack payloads, validated against `messages/*.json`.

A message is a plain dict. numpy arrays anywhere in it travel as
`{"dtype": str, "shape": [int], "data": bytes}` (C order, little-endian), never as
per-element lists; `decode` turns them back into read-only arrays that view the payload.
Fields a message type does not declare are dropped on receipt (a bag keeps the payload as
it was sent).

Speed: a node sleeps between messages while other processes use the cores, so it handles
each message with cold caches, where every step costs 3-10x its hot-loop time. That cold CPU
is most of what the bus adds to a hop, so the path touches as little as it can: msgspec's
typed decoder unpacks and checks a payload against its type's schema in one pass of C
(`wire_type` translates the JSON Schema; a 1 kB HandKeypoints in ~1 us, against ~7.5 for
msgpack's unpack and fastjsonschema's check); arrays are rebuilt, and every float checked
finite, by straight-line code generated from the schema (a generic walk of the message costs
~3x more cold); msgspec's encoder packs a message (the same bytes as msgpack's Packer,
sooner); and large messages (frames) are packed into pooled buffers that are sent as they
are (`encode_view`).
"""
from __future__ import annotations

import functools
import json
import math
import os
import threading
import time
from importlib import resources
from typing import Annotated, Any, Literal, NotRequired, TypedDict

import msgpack
import msgspec
import numpy as np

# Larger payloads are dropped unread; a 4K BGR frame is 25 MB.
MAX_MESSAGE_BYTES = int(os.environ.get("HANDMOCAP_MAX_MESSAGE_BYTES", 64 * 1024 * 1024))
_ARRAY_KEYS = frozenset(("dtype", "shape", "data"))
# A header stamp further ahead of the receiving host's clock is refused: clocks of a graph's
# hosts agree within seconds (NTP), and a stamp of 2^64 - 1 made `now - stamp` garbage downstream.
MAX_FUTURE_NS = 60 * 1_000_000_000


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


# Schema keywords that say nothing a message must satisfy
_NOTES = frozenset(("description", "title", "$comment", "$defs", "x-shape", "x-unit", "x-summary", "examples"))


def _inline_refs(node, defs: dict, depth: int = 0):
    """The schema with every local reference (`{"$ref": "#/$defs/name"}`, nothing beside it
    but notes such as a description) replaced by its definition: the same schema, in one
    piece. `$defs` stay where they are, for any reference left."""
    if depth > 64:
        raise RecursionError("recursive $ref")
    if isinstance(node, dict):
        ref = node.get("$ref")
        if isinstance(ref, str) and ref.startswith("#/$defs/") and ref[8:] in defs and set(node) - {"$ref"} <= _NOTES:
            return _inline_refs(defs[ref[8:]], defs, depth + 1)
        return {k: v if k == "$defs" else _inline_refs(v, defs, depth + 1) for k, v in node.items()}
    if isinstance(node, list):
        return [_inline_refs(v, defs, depth + 1) for v in node]
    return node


@functools.cache
def _flat_schema(type_name: str) -> dict:
    s = schema(type_name)
    try:
        return _inline_refs(s, s["$defs"])
    except RecursionError:   # a recursive schema keeps its refs
        return s


def wire_type(s: dict, where: str = "$"):
    """The msgspec type that checks what the JSON Schema `s` (a part of a type's flat schema)
    asks, for msgspec's typed decoder: unpacking and checking in one pass of C (a 1 kB
    HandKeypoints: ~1 us against ~7.5 for msgpack and fastjsonschema). The subset the messages
    use, exactly: an object (TypedDict: `required` keys must be there, `properties` checked;
    keys a type does not declare are dropped on receipt), an array (`items`, `minItems`,
    `maxItems`; a list of `items` schemas of one fixed length: a tuple), integer and number
    (`minimum`, `maximum`; a bool is neither, an integral float is no integer), string,
    boolean, `const` and `enum` (Literal), and no type at all (anything). A ValueError names
    any other keyword, so a schema the translation would check less than it says never ships
    (tests/test_codec.py translates every type)."""
    def unsupported(keys):
        raise ValueError(f"messages schema at {where}: {', '.join(sorted(keys))} has no wire_type translation")

    def bounds(t, **meta):
        meta = {k: v for k, v in meta.items() if v is not None}
        return Annotated[t, msgspec.Meta(**meta)] if meta else t

    keys = set(s) - _NOTES
    if "const" in s or "enum" in s:
        values = (s["const"],) if "const" in s else tuple(s["enum"])
        if keys - {"const", "enum", "type"} or not all(type(v) in (str, int) for v in values):
            unsupported(keys)
        return Literal[values]
    kind = s.get("type")
    if kind is None:
        if keys:
            unsupported(keys)
        return Any
    if kind == "object":
        if keys - {"type", "properties", "required", "additionalProperties"} or \
                s.get("additionalProperties", False) is not False:
            unsupported(keys)
        required = set(s.get("required", ()))
        fields = {k: wire_type(v, f"{where}.{k}") for k, v in s.get("properties", {}).items()}
        if required - set(fields):
            unsupported({f"required {sorted(required - set(fields))} without properties"})
        name = "".join(c if c.isalnum() else "_" for c in where)
        return TypedDict(name, {k: t if k in required else NotRequired[t] for k, t in fields.items()})
    if kind == "array":
        if keys - {"type", "items", "minItems", "maxItems"}:
            unsupported(keys)
        items = s.get("items", {})
        if isinstance(items, list):
            if not s.get("minItems") == s.get("maxItems") == len(items):
                unsupported({"items list of open length"})
            return tuple[tuple(wire_type(v, f"{where}[{i}]") for i, v in enumerate(items))]
        return bounds(list[wire_type(items, f"{where}[]")], min_length=s.get("minItems"), max_length=s.get("maxItems"))
    scalar = {"integer": int, "number": float, "string": str, "boolean": bool}.get(kind)
    if scalar is None or keys - ({"type", "minimum", "maximum"} if scalar in (int, float) else {"type"}):
        unsupported(keys)
    return bounds(scalar, ge=s.get("minimum"), le=s.get("maximum"))


@functools.cache
def _decoder(type_name: str) -> msgspec.msgpack.Decoder:
    """msgspec's typed decoder of a type (`wire_type` of its flat schema), shared by every
    thread of the process (msgspec's decoders are thread-safe)."""
    return msgspec.msgpack.Decoder(wire_type(_flat_schema(type_name), type_name))


_DTYPE_NAMES = {np.dtype(n): n for n in  # dtype.name is slow: a lookup table for the wire types
                ("uint8", "uint16", "int8", "int16", "int32", "int64", "float16", "float32", "float64", "bool")}
_SMALL_ARRAY_BYTES = 4096  # below this a copy (tobytes) is cheaper than a memoryview cast


def _to_wire(obj):
    if type(obj) is np.ndarray:   # the common case first: a C-ordered array of a wire dtype
        name = _DTYPE_NAMES.get(obj.dtype)   # (a big-endian dtype is not in the table)
        if name is not None and obj.flags.c_contiguous:
            return {"dtype": name, "shape": obj.shape,
                    "data": obj.tobytes() if obj.nbytes <= _SMALL_ARRAY_BYTES else memoryview(obj).cast("B")}
    if isinstance(obj, np.ndarray):
        a = obj if obj.flags.c_contiguous else np.ascontiguousarray(obj)
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        data = a.tobytes() if a.nbytes <= _SMALL_ARRAY_BYTES else memoryview(a).cast("B")
        return {"dtype": _DTYPE_NAMES.get(a.dtype) or a.dtype.name, "shape": list(a.shape), "data": data}
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


_packers = threading.local()   # encode_view's pooled Packers, per thread (a Packer is not thread-safe)


# msgspec's encoder: the same bytes as msgpack's Packer, ~0.7 us sooner a 1 kB message; like its
# decoders, safe to share between threads (msgspec 0.15 on)
_ENCODER = msgspec.msgpack.Encoder(enc_hook=_to_wire)


def encode(msg: dict, type_name: str | None = None) -> bytes:
    """Pack one message; with `type_name`, validate it first (raises MalformedMessage)."""
    payload = _ENCODER.encode(msg)
    if type_name is not None:
        decode(payload, type_name)
    return payload


def encode_view(msg: dict, type_name: str | None = None) -> memoryview:
    """Like `encode`, without the copy out of the packer: a read-only view of a pooled packer's
    buffer, for zero-copy sends of large messages (a frame). A packer is reused only once every
    view of its buffer is gone (zmq drops its own once the frame is sent): msgpack refuses to
    touch a buffer that is still exported, so a busy packer is never overwritten. Reusing warm
    buffers also spares the page faults of a fresh megabyte per message."""
    try:
        pool = _packers.pool
    except AttributeError:
        pool = _packers.pool = []
    for packer in pool:
        try:
            packer.reset()
            break
        except BufferError:   # its last payload is still being sent
            continue
    else:
        packer = msgpack.Packer(default=_to_wire, use_bin_type=True, autoreset=False)
        if len(pool) < 8:
            pool.append(packer)
    try:
        packer.pack(msg)
    except BaseException:
        packer.reset()
        raise
    view = packer.getbuffer().toreadonly()
    if type_name is not None:
        decode(view, type_name)
    return view


_DTYPES = {name: dt for dt, name in _DTYPE_NAMES.items()}


def _arrays_from_wire(obj):
    """Replace every {dtype, shape, data} map by a numpy view, in place (anywhere in `obj`)."""
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
    """A read-only view of one wire array (one the schema did not declare, so checked here)."""
    dtype, shape = v["dtype"], v["shape"]
    dt = _DTYPES.get(dtype) if type(dtype) is str else None
    if dt is None or not isinstance(shape, list) or len(shape) > 32:
        raise MalformedMessage("schema", f"not an array: dtype {dtype!r}, shape {shape!r}")
    _check_size(v, dt)
    return np.ndarray(shape, dt, v["data"])   # read-only: it views the bytes of the payload


def _check_size(v: dict, dt: np.dtype) -> None:
    shape, data = v["shape"], v["data"]
    try:
        need = math.prod(shape) * dt.itemsize
    except TypeError:
        need = None
    if not isinstance(data, bytes) or len(data) != need:
        raise MalformedMessage("array-size", f"{v['dtype']}{shape} needs {need} bytes, got "
                               f"{len(data) if isinstance(data, bytes) else type(data).__name__}")
    if not all(type(n) is int and n >= 0 for n in shape):   # the schema's "integer" lets 2.0 through
        raise MalformedMessage("array-shape", f"shape {shape!r} is not made of counts")


def _bad_array(v: dict) -> None:
    """Raise the MalformedMessage of a declared array whose bytes do not fit its dtype and shape."""
    dt = _DTYPES.get(v["dtype"]) if type(v["dtype"]) is str else None
    if dt is None:
        raise MalformedMessage("schema", f"not an array dtype: {v['dtype']!r}")
    _check_size(v, dt)
    raise MalformedMessage("array-shape", f"numpy refuses shape {v['shape']!r}")


# Where a type's arrays and floats are, read from its schema: a plan is ("array", dtype, shape)
# (dtype and shape: the schema's constants, or None), ("list", plan), ("object", {key: plan})
# (keys it does not declare never reach the converter: msgspec drops them), ("float",) (a
# number), ("any",) (a part the schema leaves open: walked generically) or None (neither).
_ANY = ("any",)
_FLOAT = ("float",)   # a number: no array, but a float the finite check reads


def _plan(s: dict):
    """The plan of a part of a flat schema that `wire_type` translates (it refuses $ref, anyOf,
    patternProperties and the like, so none reaches here)."""
    t = s.get("type")
    if t == "object":
        props = s.get("properties", {})
        if set(s.get("required", ())) >= _ARRAY_KEYS and set(props) == _ARRAY_KEYS \
                and s.get("additionalProperties") is False:
            dtype = props["dtype"].get("const") if isinstance(props["dtype"], dict) else None
            sh = props["shape"] if isinstance(props["shape"], dict) else {}
            items = sh.get("items")
            shape = None
            if isinstance(items, list) and sh.get("minItems") == len(items) == sh.get("maxItems") \
                    and all(isinstance(i, dict) and type(i.get("const")) is int for i in items):
                shape = tuple(i["const"] for i in items)
            return ("array", dtype if dtype in _DTYPES else None, shape)
        inner = {k: p for k, p in ((k, _plan(v)) for k, v in props.items()) if p is not None}
        return ("object", inner) if inner else None
    if t == "array":
        items = s.get("items")
        if isinstance(items, dict):
            p = _plan(items)
            return None if p is None else ("list", p)
        return _ANY if items is not None else ("list", _ANY)
    if t is None and "enum" not in s and "const" not in s:
        return _ANY
    return _FLOAT if t == "number" else None   # a scalar: holds no array


def _arrays_only(plan):
    """`plan` without its floats (what the converter has nothing to do for), or None."""
    if plan is None or plan is _FLOAT:
        return None
    if plan[0] == "object":
        inner = {k: p for k, p in ((k, _arrays_only(sub)) for k, sub in plan[1].items()) if p is not None}
        return ("object", inner) if inner else None
    if plan[0] == "list":
        inner = _arrays_only(plan[1])
        return None if inner is None else ("list", inner)
    return plan


def _emit_walk(lines: list, names, var: str, plan, ind: str, target: str | None, leaf) -> None:
    """Append to `lines` straight-line code that reaches every leaf of `plan` under the variable
    `var` (an object's keys through .get, a list's items in a loop); `leaf(var, plan, ind,
    target)` appends a leaf's own lines (`target`: the expression that assigns in its place).
    `names`: an iterator of fresh numbers for the code's variables."""
    kind = plan[0]
    if kind == "object":
        for key, sub in plan[1].items():
            v = f"v{next(names)}"
            lines.append(f"{ind}{v} = {var}.get({key!r})")
            lines.append(f"{ind}if {v} is not None:")
            _emit_walk(lines, names, v, sub, ind + "    ", f"{var}[{key!r}]", leaf)
    elif kind == "list":
        i, x = f"i{next(names)}", f"x{next(names)}"
        lines.append(f"{ind}for {i}, {x} in enumerate({var}):")
        _emit_walk(lines, names, x, plan[1], ind + "    ", f"{var}[{i}]", leaf)
    else:
        leaf(var, plan, ind, target)


def _converter_source(plan, tail: bool = False) -> tuple[str, dict]:
    """Python source of `convert(m)`, which turns the arrays of a schema-checked message into
    views in place, following `plan` in straight-line code (a generic walk costs ~3x more
    with cold caches), and the constants it uses. With `tail`: `convert(m, tail)`, where the
    array whose data is the `_TAIL_TOKEN` placeholder gets `tail` (a view of the payload's last
    binary) as its data; it returns how many arrays took it (the caller wants exactly 1)."""
    env = {"_TOK": _TAIL_TOKEN, "_nd": np.ndarray, "_DTYPES": _DTYPES, "_bad": _bad_array, "_prod": math.prod,
           "_any": lambda v: _arrays_from_wire({0: v})[0]}
    lines = ["def convert(m, _tail):", "    _took = 0"] if tail else ["def convert(m):"]
    names = iter(range(1 << 30))

    def const(value) -> str:
        name = f"_c{next(names)}"
        env[name] = value
        return name

    def leaf(var: str, plan, ind: str, target: str | None) -> None:
        kind = plan[0]
        if kind == "array":
            _, dtype, shape = plan
            d = f"d{next(names)}"
            lines.append(f"{ind}{d} = {var}['data']")
            ok_type = f"type({d}) is not bytes"
            if tail:   # the placeholder of the payload's last binary: its view instead
                lines.append(f"{ind}if type({d}) is bytes and len({d}) == {len(_TAIL_TOKEN)} and {d} == _TOK:")
                lines.append(f"{ind}    {d} = _tail")
                lines.append(f"{ind}    _took += 1")
                ok_type = f"(type({d}) is not bytes and {d} is not _tail)"
            if dtype is not None:
                dt = const(_DTYPES[dtype])
            else:
                dt = f"t{next(names)}"
                lines.append(f"{ind}{dt} = _DTYPES.get({var}['dtype'])")
                lines.append(f"{ind}if {dt} is None:")
                lines.append(f"{ind}    _bad({var})")
            if shape is not None:
                sh = const(shape)
                size = str(math.prod(shape) * _DTYPES[dtype].itemsize) if dtype is not None \
                    else f"{math.prod(shape)} * {dt}.itemsize"
            else:
                sh = f"{var}['shape']"
                size = f"_prod({sh}) * {dt}.itemsize"
            lines.append(f"{ind}if {ok_type} or len({d}) != {size}:")
            lines.append(f"{ind}    _bad({var})")
            if shape is None:   # numpy refuses some shapes of counts ("array is too big")
                lines.append(f"{ind}try:")
                lines.append(f"{ind}    {target} = _nd({sh}, {dt}, {d})")
                lines.append(f"{ind}except (TypeError, ValueError):")
                lines.append(f"{ind}    _bad({var})")
            else:
                lines.append(f"{ind}{target} = _nd({sh}, {dt}, {d})")
        else:   # any
            lines.append(f"{ind}{target} = _any({var})")

    if plan is not None:
        _emit_walk(lines, names, "m", plan, "    ", "m", leaf)
    lines.append("    return _took" if tail else "    return m")
    return "\n".join(lines) + "\n", env


@functools.cache
def _converter(type_name: str, tail: bool = False):
    """The compiled `convert(m)` of a type; with `tail`, `convert(m, view)` (see `decode`)."""
    source, env = _converter_source(_arrays_only(_plan(_flat_schema(type_name))), tail)
    exec(compile(source, f"<handmocap.runtime.codec converter for {type_name}>", "exec"), env)
    return env["convert"]


def _finite_source(plan) -> tuple[str, dict]:
    """Python source of `finite(m)`: whether every float and float array at the places `plan`
    declares is finite, read in straight-line code (the generic walk, `_all_finite`, costs
    ~2 us more a message), all arrays in one numpy call."""
    env = {"_isfinite": math.isfinite, "_arrays_ok": _finite_arrays, "_walk": _all_finite}
    lines = ["def finite(m):", "    _fl = []"]
    names = iter(range(1 << 30))

    def leaf(var: str, plan, ind: str, target: str | None) -> None:
        kind = plan[0]
        if kind == "array":
            dtype = plan[1]
            if dtype is None:
                lines.append(f"{ind}if {var}.dtype.kind == 'f':")
                lines.append(f"{ind}    _fl.append({var}.reshape(-1))")
            elif _DTYPES[dtype].kind == "f":
                lines.append(f"{ind}_fl.append({var}.reshape(-1))")
            else:
                lines.append(f"{ind}pass")
        elif kind == "float":
            lines.append(f"{ind}if not _isfinite({var}):")
            lines.append(f"{ind}    return False")
        else:   # any
            lines.append(f"{ind}if not _walk({var}):")
            lines.append(f"{ind}    return False")

    if plan is not None:
        _emit_walk(lines, names, "m", plan, "    ", None, leaf)
    lines.append("    return _arrays_ok(_fl)")
    return "\n".join(lines) + "\n", env


@functools.cache
def _finite(type_name: str):
    """The compiled `finite(m)` of a type (see `_finite_source`)."""
    source, env = _finite_source(_plan(_flat_schema(type_name)))
    exec(compile(source, f"<handmocap.runtime.codec finite check for {type_name}>", "exec"), env)
    return env["finite"]


def _finite_arrays(arrays: list) -> bool:
    if not arrays:
        return True
    return bool(np.isfinite(arrays[0] if len(arrays) == 1 else np.concatenate(arrays)).all())


_DECODERS: dict = {}   # type name -> (msgspec decoder, convert)
_TAIL_MIN = 65536   # a payload whose last binary is at least this long is decoded without copying it
_TAIL_TOKEN = b"\x00handmocap-tail\x00"   # 16 bytes: where that binary was, in the message unpacked without it
_TAIL_SCAN = 4096   # its header must start this near the payload's start (a frame's few small fields)


def _tail_start(payload) -> int:
    """Where the bin32 that runs to the payload's very end starts (its 0xc6 header), or -1.

    Only a candidate: a 0xc6 byte inside another item with the right 4 bytes after it would
    be one too, which is why `decode` takes the split only when the message unpacked with a
    placeholder there is whole, valid and has exactly one array on the placeholder."""
    n = len(payload)
    head = bytes(payload[:min(n, _TAIL_SCAN)])
    i = head.find(b"\xc6")
    while 0 <= i <= len(head) - 5:
        if int.from_bytes(head[i + 1:i + 5], "big") == n - i - 5:
            return i
        i = head.find(b"\xc6", i + 1)
    return -1


def _decode_tail(payload, type_name: str) -> dict | None:
    """`decode` of a large payload without copying its last binary (a frame's pixels): msgpack
    copies every binary it unpacks (921 kB for a 640x480 frame: ~0.2-0.3 ms with cold caches,
    most of the receiving node's cost of a frame). The small part before it is unpacked with
    a 16-byte placeholder instead, and the array on the placeholder views the payload in
    place (read-only). None where that does not give exactly the message the full unpack
    would (any doubt: the caller unpacks the whole payload, and its errors are the ones reported).

    Sound because msgpack is read front to back: if `head + placeholder` unpacks to one whole
    item with the placeholder intact as a binary, the head's items end exactly where the
    bin32 starts, so the full payload is that same item with the bin32's bytes there."""
    i = _tail_start(payload)
    if i < 0:
        return None
    try:
        raw = _decoder(type_name).decode(bytes(payload[:i]) + b"\xc4\x10" + _TAIL_TOKEN)
        took = _converter(type_name, True)(raw, memoryview(payload)[i + 5:].toreadonly())
    except Exception:
        return None
    return raw if took == 1 else None


def decode(payload: bytes, type_name: str, max_bytes: int = MAX_MESSAGE_BYTES) -> dict:
    """Unpack and validate one payload of type `type_name`; arrays come back as numpy views.

    Raises MalformedMessage, and nothing else, whatever the bytes (reason: oversized, msgpack,
    schema, array-size, array-shape, too-deep, unknown-type, or inconsistent: a message that
    fits its schema but not itself, see CONSISTENCY; not-finite: a NaN or inf anywhere;
    stamp-future: a stamp more than MAX_FUTURE_NS ahead of this host's clock).
    """
    try:
        msg = _decode(payload, type_name, max_bytes)
        where = non_finite(msg, type_name)
        if where is not None:
            raise MalformedMessage("not-finite", f"{where} has NaN or inf")
        check = CONSISTENCY.get(type_name)
        if check is not None:
            check(msg)
        stamp = msg["header"]["stamp_ns"]
        if stamp > time.time_ns() + MAX_FUTURE_NS:
            raise MalformedMessage("stamp-future", f"header.stamp_ns {stamp} is {(stamp - time.time_ns()) / 1e9:.3g} s "
                                                   f"ahead of this host's clock (limit {MAX_FUTURE_NS / 1e9:g} s)")
        return msg
    except MalformedMessage:
        raise
    except RecursionError:
        raise MalformedMessage("too-deep", "nested deeper than the decoder follows") from None
    except Exception as e:   # numpy's "array is too big", "maximum dimension exceeded", ...
        raise MalformedMessage("array-shape", f"{type(e).__name__}: {str(e)[:200]}") from None


def decode_trusted(payload, type_name: str) -> dict:
    """`decode` of a payload this process's own code encoded (a node of the same container,
    over inproc://): unpacked by the same typed decoder (the schema's check comes with the
    unpacking, at no extra cost), arrays as views, without the walks that guard against what
    other processes send (NaN and inf, consistency, stamp). A node's publish() already refused
    NaN and inf. Raises MalformedMessage on a payload that does not unpack or fit its type (a
    bug: never from a running node)."""
    try:
        decoder, convert = _DECODERS[type_name]
    except KeyError:
        return decode(payload, type_name)   # its first message (and an unknown type's error)
    if len(payload) >= _TAIL_MIN:
        msg = _decode_tail(payload, type_name)
        if msg is not None:
            return msg
    try:
        return convert(decoder.decode(payload))
    except Exception as e:
        raise MalformedMessage("msgpack", f"{type(e).__name__}: {e}") from None


def _image_consistent(m: dict) -> None:
    """An Image's data agrees with its encoding, width and height."""
    data, enc, w, h = m["data"], m["encoding"], m["width"], m["height"]
    want = {"bgr8": (h, w, 3), "rgb8": (h, w, 3), "mono8": (h, w)}.get(enc)
    if want is not None and data.shape != want:
        raise MalformedMessage("inconsistent", f"{enc} image {w}x{h} needs data {want}, got {data.shape}")
    if enc == "jpeg" and (data.ndim != 1 or data.size < 4):
        raise MalformedMessage("inconsistent", f"jpeg image data must be a (N,) byte stream, got {data.shape}")


def non_finite(obj, type_name: str | None = None) -> str | None:
    """Where the first NaN or inf of a message is ("hands[1].beta"), or None. Every float of
    every type must be finite: a NaN that passes a hop reaches every subscriber. Runs on every
    message at both ends of a hop, so the usual answer (none) comes from a quick check: with
    `type_name`, the type's generated one, which reads the places its schema declares (what a
    receiver keeps: the others are dropped on receipt); else the generic walk (`_all_finite`).
    The walk that names the place runs only when there is one."""
    if type_name is not None:
        try:
            if _finite(type_name)(obj):
                return None
        except Exception:   # a body that does not fit its type (publish checks it later, if asked)
            pass
    elif _all_finite(obj):
        return None
    return _first_non_finite(obj)


_NDARRAY = np.ndarray
_PLAIN_LEAVES = frozenset((str, int, bool, bytes, type(None)))
_WALK_LIMIT = 100_000   # values in one message (an array counts once); a message has ~20-100


def _all_finite(obj) -> bool:
    """Whether every float and float array in obj (dicts and lists, any depth) is finite: one
    walk without paths, and all float arrays checked in one numpy call (a two-hand message
    has eight: each call costs ~1 us, more than the check)."""
    stack, arrays = [obj], []
    pop, extend = stack.pop, stack.extend
    steps = 0
    while stack:
        steps += 1
        if steps > _WALK_LIMIT:   # a cycle (a publish() body that holds itself): the named walk raises on it
            return False
        o = pop()
        kind = type(o)   # the exact types first (a decoded message holds nothing else), then subclasses
        if kind is dict:
            extend(o.values())
        elif kind is list:
            extend(o)
        elif kind is float:
            if not math.isfinite(o):
                return False
        elif kind is _NDARRAY:
            if o.dtype.kind == "f":
                arrays.append(o.reshape(-1))
        elif kind in _PLAIN_LEAVES:
            continue
        elif isinstance(o, dict):
            extend(o.values())
        elif isinstance(o, list):
            extend(o)
        elif isinstance(o, float):
            if not math.isfinite(o):
                return False
        elif isinstance(o, np.ndarray) and o.dtype.kind == "f":
            arrays.append(o.reshape(-1))
    if not arrays:
        return True
    return bool(np.isfinite(arrays[0] if len(arrays) == 1 else np.concatenate(arrays)).all())


def _first_non_finite(obj, path: str = "") -> str | None:
    """non_finite's walk that names the place (only where there is one)."""
    if isinstance(obj, np.ndarray):
        return None if obj.dtype.kind != "f" or np.isfinite(obj).all() else path
    if isinstance(obj, float):
        return None if math.isfinite(obj) else path
    if isinstance(obj, dict):
        for k, v in obj.items():
            where = _first_non_finite(v, f"{path}.{k}" if path else str(k))
            if where is not None:
                return where
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            where = _first_non_finite(v, f"{path}[{i}]")
            if where is not None:
                return where
    return None


def _camera_info_consistent(m: dict) -> None:
    K = m["K"]
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.isfinite(m["distortion"]).all():
        raise MalformedMessage("inconsistent", "K needs positive finite focal lengths, finite entries")


# Checks past the schema, per type: what a schema cannot say (an image's bytes against its size,
# K's focal lengths). A message failing one is dropped like a malformed one; so is any message
# with a NaN or inf anywhere (`non_finite`) or a stamp from the future (MAX_FUTURE_NS).
CONSISTENCY = {
    "Image": _image_consistent,
    "CameraInfo": _camera_info_consistent,
}


def _decode(payload, type_name: str, max_bytes: int) -> dict:
    if len(payload) > max_bytes:
        raise MalformedMessage("oversized", f"{len(payload)} bytes > limit {max_bytes}")
    try:
        decoder, convert = _DECODERS[type_name]
    except KeyError:
        try:
            decoder, convert = _DECODERS[type_name] = (_decoder(type_name), _converter(type_name))
        except KeyError as e:
            raise MalformedMessage("unknown-type", str(e)) from None
    if len(payload) >= _TAIL_MIN:
        msg = _decode_tail(payload, type_name)
        if msg is not None:
            return msg
    try:
        raw = decoder.decode(payload)
    except msgspec.ValidationError as e:   # unpacked, but not what the schema asks
        raise MalformedMessage("schema", str(e)) from None
    except RecursionError:
        raise   # decode's "too-deep"
    except Exception as e:   # not msgpack (msgspec.DecodeError), or nested past its depth limit
        raise MalformedMessage("msgpack", f"{type(e).__name__}: {e}") from None
    return convert(raw)


def header(seq: int, frame_id: str = "camera", stamp_ns: int | None = None) -> dict:
    """The header every message starts with (messages/common.json `header`): capture stamp, sequence, frame id."""
    return {"stamp_ns": time.time_ns() if stamp_ns is None else int(stamp_ns), "seq": int(seq),
            "frame_id": frame_id}
