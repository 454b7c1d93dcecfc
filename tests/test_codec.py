import msgpack
import msgspec
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from conftest import paths_in
from handmocap.runtime import codec


def keypoints_msg(n_hands=1):
    rng = np.random.default_rng(0)
    hand = {"track_id": 3, "handedness": "left", "score": 0.75, "bbox": np.array([1, 2, 30, 40], np.float32),
            "uv": rng.random((21, 2), dtype=np.float32), "confidence": np.ones(21, np.float32),
            "xyz_rel": rng.random((21, 3), dtype=np.float32)}
    return {"header": codec.header(7, "camera"), "width": 640, "height": 480, "hands": [hand] * n_hands}


def test_round_trip_keeps_arrays_exactly():
    msg = keypoints_msg(2)
    out = codec.decode(codec.encode(msg, "HandKeypoints"), "HandKeypoints")
    assert out["header"] == msg["header"]
    for a, b in zip(out["hands"], msg["hands"]):
        for k in ("bbox", "uv", "confidence", "xyz_rel"):
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape
            np.testing.assert_array_equal(a[k], b[k])


def test_arrays_travel_as_raw_bytes_not_lists():
    raw = msgpack.unpackb(codec.encode(keypoints_msg()))
    uv = raw["hands"][0]["uv"]
    assert set(uv) == {"dtype", "shape", "data"} and isinstance(uv["data"], bytes)
    assert uv["shape"] == [21, 2] and len(uv["data"]) == 21 * 2 * 4


def test_non_contiguous_and_big_endian_arrays_are_encoded_right():
    a = np.arange(42, dtype=">f4").reshape(21, 2)
    msg = keypoints_msg()
    msg["hands"][0]["uv"] = a
    msg["hands"][0]["xyz_rel"] = np.arange(126, dtype=np.float32).reshape(21, 6)[:, ::2]
    out = codec.decode(codec.encode(msg), "HandKeypoints")["hands"][0]
    np.testing.assert_array_equal(out["uv"], a)
    np.testing.assert_array_equal(out["xyz_rel"], msg["hands"][0]["xyz_rel"])


@pytest.mark.parametrize("mutate, reason", [
    (lambda m: m["hands"][0].pop("uv"), "schema"),
    (lambda m: m["hands"][0].update(uv=np.zeros((20, 2), np.float32)), "schema"),
    (lambda m: m["hands"][0].update(uv=np.zeros((21, 2), np.float64)), "schema"),
    (lambda m: m["hands"][0].update(handedness="both"), "schema"),
    (lambda m: m["header"].update(stamp_ns=-1), "schema"),
    (lambda m: m.pop("header"), "schema"),
])
def test_schema_violations_are_malformed(mutate, reason):
    msg = keypoints_msg()
    mutate(msg)
    with pytest.raises(codec.MalformedMessage) as e:
        codec.decode(codec.encode(msg), "HandKeypoints")
    assert e.value.reason == reason


def test_array_with_wrong_byte_count_is_malformed():
    raw = msgpack.unpackb(codec.encode(keypoints_msg()))
    raw["hands"][0]["uv"]["data"] = raw["hands"][0]["uv"]["data"][:-4]
    with pytest.raises(codec.MalformedMessage) as e:
        codec.decode(msgpack.packb(raw), "HandKeypoints")
    assert e.value.reason == "array-size"


def test_float_shapes_are_malformed_and_never_crash_the_decoder():
    """A shape written as floats (2.0) is no shape of counts, fixed or free: one clear error
    (numpy would raise TypeError and kill the node)."""
    raw = msgpack.unpackb(codec.encode(keypoints_msg()))
    raw["hands"][0]["uv"]["shape"] = [21.0, 2.0]
    with pytest.raises(codec.MalformedMessage) as e:
        codec.decode(msgpack.packb(raw), "HandKeypoints")
    assert e.value.reason == "schema" and "hands[0].uv.shape[0]" in str(e.value)
    img = {"header": codec.header(0), "encoding": "mono8", "width": 2, "height": 2,
           "data": {"dtype": "uint8", "shape": [2.0, 2.0], "data": bytes(4)}}
    with pytest.raises(codec.MalformedMessage) as e:
        codec.decode(msgpack.packb(img), "Image")
    assert e.value.reason == "schema"


def test_fields_a_type_does_not_declare_are_dropped_on_receipt():
    """A newer publisher's fields (or anyone's) reach a subscriber as absent, whatever they
    hold, even inside an array; the declared ones arrive as they were sent."""
    msg = keypoints_msg()
    msg["extra"] = {"nested": [np.arange(3, dtype=np.int32)], "bad": {"dtype": "no-such-dtype", "shape": [1]}}
    msg["header"]["note"] = np.ones(2, np.float64)
    msg["hands"][0]["more"] = np.zeros((2, 2), np.uint8)
    raw = msgpack.unpackb(codec.encode(msg))
    raw["hands"][0]["uv"]["note"] = "inside an array"
    out = codec.decode(msgpack.packb(raw), "HandKeypoints")
    assert set(out) == {"header", "width", "height", "hands"} and set(out["header"]) == {"stamp_ns", "seq", "frame_id"}
    assert "more" not in out["hands"][0] and out["hands"][0]["uv"].dtype == np.float32
    np.testing.assert_array_equal(out["hands"][0]["uv"], msg["hands"][0]["uv"])
    assert codec.decode_trusted(codec.encode(msg), "HandKeypoints").keys() == out.keys()


def test_decoded_arrays_are_read_only_views():
    out = codec.decode(codec.encode(keypoints_msg()), "HandKeypoints")
    assert not out["hands"][0]["uv"].flags.writeable


def test_encode_view_is_the_same_payload_and_never_reuses_a_buffer_in_use():
    big = {"header": codec.header(1), "encoding": "bgr8", "width": 640, "height": 480,
           "data": np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)}
    first = codec.encode_view(big, "Image")
    assert first.readonly and bytes(first) == codec.encode(big)
    kept = bytes(first)
    others = [codec.encode_view({**big, "header": codec.header(i)}) for i in range(2, 12)]   # pool full, then more
    assert bytes(first) == kept   # still exported (as to zmq): untouched
    assert len({bytes(o[:200]) for o in others}) == len(others)
    del first, others
    again = codec.encode_view(big)
    assert bytes(again) == kept


def test_oversized_and_unknown_type():
    with pytest.raises(codec.MalformedMessage) as e:
        codec.decode(b"\x80" * 100, "Blob", max_bytes=10)
    assert e.value.reason == "oversized"
    with pytest.raises(codec.MalformedMessage) as e:
        codec.decode(codec.encode(keypoints_msg()), "NoSuchType")
    assert e.value.reason == "unknown-type"


def test_every_schema_compiles_and_names_its_type():
    for t in codec.message_types():
        assert codec.schema(t)["title"] == t


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2000), st.sampled_from(["Image", "HandKeypoints", "HandPose", "CameraInfo", "Blob"]))
def test_fuzzed_payloads_only_ever_raise_malformed(payload, type_name):
    try:
        codec.decode(payload, type_name)
    except codec.MalformedMessage:
        pass


@settings(max_examples=200, deadline=None)
@given(st.recursive(st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=8)
                    | st.binary(max_size=16),
                    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4),
                    max_leaves=30))
def test_fuzzed_structures_only_ever_raise_malformed(obj):
    for type_name in ("HandKeypoints", "Image"):
        try:
            codec.decode(msgpack.packb(obj), type_name)
        except codec.MalformedMessage:
            pass


def _example(s):
    """A minimal instance of the flat schema part `s`, in wire form (arrays as dtype/shape/data)."""
    if "const" in s:
        return s["const"]
    if "enum" in s:
        return s["enum"][0]
    kind = s.get("type")
    if kind == "object":
        return {k: _example(v) for k, v in s.get("properties", {}).items()}
    if kind == "array":
        items = s.get("items", {})
        return [_example(i) for i in items] if isinstance(items, list) else [_example(items)] * max(1, s.get("minItems", 1))
    return {"integer": s.get("minimum", 0), "number": float(s.get("minimum", 0)), "string": "x",
            "boolean": False}.get(kind, b"")


@pytest.mark.parametrize("type_name", codec.message_types())
def test_msgspecs_check_of_every_type_refuses_whatever_its_json_schema_refuses(type_name):
    """messages/*.json stay the contract; the decoder checks it through codec.wire_type. Every
    value at every place of a minimal message, replaced by each of a few wrong ones or removed:
    where the JSON Schema (fastjsonschema) refuses it, msgspec's decoder does too; where the
    schema takes it, so does the decoder, but for a float with an integral value where an
    integer belongs (no count: the decoder refuses it) and keys an array may not have (dropped)."""
    import copy

    import fastjsonschema
    flat = codec._flat_schema(type_name)
    schema_ok = fastjsonschema.compile(flat)
    decoder = codec._decoder(type_name)
    base = _example(flat)
    schema_ok(base)
    decoder.decode(msgpack.packb(base))
    wrong = (None, True, -1, 0, 3, 1.5, 2.0, 10**19, "s", "float64", b"b", [], [0], {}, {"k": 1})
    for path in list(paths_in(base))[1:]:
        for value in (*wrong, "remove"):
            msg = copy.deepcopy(base)
            parent = msg
            for k in path[:-1]:
                parent = parent[k]
            if value == "remove":
                if isinstance(parent, list):
                    continue
                del parent[path[-1]]
            else:
                parent[path[-1]] = value
            try:
                schema_ok(msg)
                schema_says = True
            except fastjsonschema.JsonSchemaException:
                schema_says = False
            try:
                decoder.decode(msgpack.packb(msg, use_bin_type=True))
                decoder_says = True
            except msgspec.ValidationError:
                decoder_says = False
            if schema_says != decoder_says:
                assert schema_says and value == 2.0, (type_name, path, value, schema_says, decoder_says)


def test_a_schema_construct_the_decoder_cannot_check_is_an_error_not_a_looser_check():
    for s in ({"type": "string", "pattern": "^a"}, {"anyOf": [{"type": "integer"}, {"type": "string"}]},
              {"type": "object", "properties": {}, "additionalProperties": {"type": "integer"}},
              {"type": "array", "items": [{"const": 1}], "maxItems": 3}):
        with pytest.raises(ValueError, match="no wire_type translation"):
            codec.wire_type(s)


def test_the_typed_finite_check_names_a_nan_where_the_body_does_not_fit_its_type_too():
    """codec.non_finite(body, type) reads the places the type declares; a body that does not fit
    (a list where an array belongs, as a careless publisher may send) falls back to the walk."""
    msg = keypoints_msg(2)
    assert codec.non_finite(msg, "HandKeypoints") is None
    msg["hands"][1] = {**msg["hands"][1], "score": float("inf")}
    assert codec.non_finite(msg, "HandKeypoints") == "hands[1].score"
    msg = keypoints_msg()
    msg["hands"][0]["uv"] = [[float("nan"), 0.0]] * 21
    assert codec.non_finite(msg, "HandKeypoints") == "hands[0].uv[0][0]"
    msg["hands"][0]["uv"] = np.zeros((21, 2), np.float32)
    assert codec.non_finite(msg, "HandKeypoints") is None
