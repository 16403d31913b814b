"""Property-based round trips of every stream schema, and rejection of malformed payloads.

Messages are generated from each class's declared fields (array dtype/shape metadata and
plain value kinds), so a stream added later is covered without touching this file.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import gaitflow.schemas as schemas_pkg
import msgpack
import numpy as np
import pytest
from gaitflow.schemas import STREAMS, Header, Message, decode, decode_any, json_schema
from gaitflow.schemas import messages_equal as equal
from gaitflow.schemas._codec import array_field
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gaitflow.errors import SchemaError, SchemaVersionError

ALL = sorted(STREAMS)
SETTINGS = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)

INT64 = st.integers(-(2**63), 2**63 - 1)
NONNEG64 = st.integers(0, 2**63 - 1)
# Plain JSON-like values, as msgpack gives them back (lists, str-keyed maps, no NaN inside
# containers: NaN != NaN would make container equality meaningless).
SCALARS = st.none() | st.booleans() | INT64 | st.floats(allow_nan=False) | st.text(max_size=8)
JSONISH = st.recursive(
    SCALARS,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=12,
)


def _array(dtype: str, shape: tuple[int | None, ...]) -> st.SearchStrategy[np.ndarray]:
    dt = np.dtype(dtype)
    # Free axes take 0..4 so empty arrays come up often; fixed axes keep their size.
    shapes = st.tuples(*(st.just(s) if s is not None else st.integers(0, 4) for s in shape))
    if dt.kind == "f":
        elements = st.floats(allow_nan=True, allow_infinity=True, width=dt.itemsize * 8)
    else:
        elements = None
    return shapes.flatmap(lambda shp: hnp.arrays(dt, shp, elements=elements))


def _value(kinds: tuple[type, ...]) -> st.SearchStrategy[Any]:
    options = []
    for k in kinds:
        if k is float:
            options.append(st.floats(allow_nan=True, allow_infinity=True))
        elif k is bool:
            options.append(st.booleans())
        elif k is int:
            options.append(INT64)
        elif k is str:
            options.append(st.text(max_size=12))
        elif k is list:
            options.append(st.lists(JSONISH, max_size=4))
        elif k is dict:
            options.append(st.dictionaries(st.text(max_size=6), JSONISH, max_size=4))
        elif k is type(None):
            options.append(st.none())
        else:  # a new value kind needs a strategy here
            raise AssertionError(f"no strategy for value kind {k}")
    return st.one_of(options)


def headers(cls: type[Message]) -> st.SearchStrategy[Header]:
    return st.builds(
        lambda cam, trial, frame, cap, last: cls.make_header(cam, trial, frame, cap, last),
        st.text(max_size=10),
        st.text(max_size=10),
        INT64,
        NONNEG64,
        st.booleans(),
    )


def messages(cls: type[Message]) -> st.SearchStrategy[Message]:
    fields: dict[str, st.SearchStrategy[Any]] = {"header": headers(cls)}
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        if "array" in f.metadata:
            fields[f.name] = _array(*f.metadata["array"])
        else:
            fields[f.name] = _value(f.metadata["value"])
    return st.fixed_dictionaries(fields).map(lambda kw: cls(**kw))


def _required(f: dataclasses.Field[Any]) -> bool:
    return f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING


def _array_fields(cls: type[Message]) -> list[dataclasses.Field[Any]]:
    return [f for f in dataclasses.fields(cls) if "array" in f.metadata]


def _value_fields(cls: type[Message]) -> list[dataclasses.Field[Any]]:
    return [f for f in dataclasses.fields(cls) if "value" in f.metadata]


def _repack(payload: bytes, edit) -> bytes:
    """Decode a payload with plain msgpack, let ``edit`` change the parts, pack it again."""
    parts = msgpack.unpackb(payload, raw=False)
    edit(parts)
    return msgpack.packb(parts, use_bin_type=True)


# ----------------------------------------------------------------------- round trips


@pytest.mark.parametrize("name", ALL)
def test_round_trip(name: str) -> None:
    cls = STREAMS[name]

    @SETTINGS
    @given(messages(cls), NONNEG64)
    def check(msg: Message, pub: int) -> None:
        payload = msg.encode(publish_ns=pub)
        back = decode(cls, payload)
        assert equal(msg, back), f"{name}: {msg} != {back}"
        assert back.header.publish_ns == pub
        assert back.header.schema == name and back.header.version == cls.VERSION
        assert equal(decode_any(payload), back)
        # Any buffer type works, and decoding a copy gives the same message.
        assert equal(decode(cls, memoryview(bytearray(payload))), back)
        for f in _array_fields(cls):
            a = getattr(back, f.name)
            assert a.dtype.str == f.metadata["array"][0]
            assert not a.flags.writeable  # zero-copy views of the payload

    check()


@pytest.mark.parametrize("name", ALL)
def test_round_trip_all_nan_and_empty(name: str) -> None:
    """Float arrays full of NaN, free axes empty, float scalars NaN: all survive."""
    cls = STREAMS[name]
    kw: dict[str, Any] = {"header": cls.make_header("cam0", "walk-01", 7, 123, last=True)}
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        if "array" in f.metadata:
            dtype, shape = f.metadata["array"]
            shp = tuple(0 if s is None else s for s in shape)
            kind = np.dtype(dtype).kind
            kw[f.name] = np.full(shp, np.nan) if kind == "f" else np.zeros(shp, dtype)
        elif float in f.metadata["value"]:
            kw[f.name] = float("nan")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            kw[f.name] = f.metadata["value"][0]()
    msg = cls(**kw)
    back = decode(cls, msg.encode())
    assert equal(msg, back)
    for f in _value_fields(cls):
        if float in f.metadata["value"]:
            assert math.isnan(getattr(back, f.name))


def test_messages_equal_can_fail() -> None:
    """The equality used above does see a changed element, NaN vs number and shape."""
    from gaitflow.schemas import LabelledMarkers

    h = LabelledMarkers.make_header("cam0", "walk-01", 0, 0)
    pos = np.zeros((20, 3))
    a = LabelledMarkers(header=h, position=pos, pixel=np.zeros((20, 2)), blob=np.zeros(20, "i4"))
    pos2 = pos.copy()
    pos2[3, 1] = np.nan
    b = dataclasses.replace(a, position=pos2)
    assert equal(a, a) and not equal(a, b)
    assert not equal(a, dataclasses.replace(a, direction=1))
    assert not equal(a, dataclasses.replace(a, header=dataclasses.replace(h, frame=1)))


# ----------------------------------------------------------------------- malformed payloads


def _example(cls: type[Message]) -> Message:
    """A small valid message with one element on every free axis."""
    kw: dict[str, Any] = {"header": cls.make_header("cam0", "walk-01", 3, 1_000, False)}
    for f in dataclasses.fields(cls):
        if "array" in f.metadata:
            dtype, shape = f.metadata["array"]
            kw[f.name] = np.ones(tuple(1 if s is None else s for s in shape), dtype)
        elif "value" in f.metadata and _required(f):
            kw[f.name] = f.metadata["value"][0]()
    return cls(**kw)


@pytest.mark.parametrize("name", ALL)
def test_every_truncation_is_rejected(name: str) -> None:
    cls = STREAMS[name]
    payload = _example(cls).encode()
    cuts = sorted(set(range(0, min(len(payload), 300))) | set(range(300, len(payload), 97)))
    for cut in cuts:
        with pytest.raises(SchemaError) as ei:
            decode(cls, payload[:cut])
        assert ei.value.stream == name, cut


@pytest.mark.parametrize("name", ALL)
def test_random_bytes_are_rejected_with_schema_error(name: str) -> None:
    cls = STREAMS[name]

    @SETTINGS
    @given(st.binary(max_size=200))
    def check(junk: bytes) -> None:
        with pytest.raises(SchemaError) as ei:
            decode(cls, junk)
        assert ei.value.stream == name

    check()


@pytest.mark.parametrize("name", ALL)
def test_corrupted_bytes_raise_only_schema_error(name: str) -> None:
    """Flip bytes of a valid payload: it decodes or raises SchemaError, nothing else."""
    cls = STREAMS[name]
    payload = _example(cls).encode()

    @SETTINGS
    @given(st.lists(st.tuples(st.integers(0, len(payload) - 1), st.integers(0, 255)), max_size=4))
    def check(flips: list[tuple[int, int]]) -> None:
        b = bytearray(payload)
        for i, v in flips:
            b[i] = v
        try:
            decode(cls, bytes(b))
        except SchemaError as exc:
            assert exc.stream == name

    check()


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("delta", [-1, 1])
def test_old_and_new_versions_are_rejected(name: str, delta: int) -> None:
    cls = STREAMS[name]

    def bump(parts: list[Any]) -> None:
        parts[0]["version"] = cls.VERSION + delta

    bad = _repack(_example(cls).encode(), bump)
    with pytest.raises(SchemaVersionError) as ei:
        decode(cls, bad)
    assert ei.value.stream == name and ei.value.field == "header.version"
    assert str(cls.VERSION + delta) in str(ei.value)


@pytest.mark.parametrize("name", ALL)
def test_repacked_message_still_decodes(name: str) -> None:
    """A writer other than ours (any msgpack packer, small bin types) is readable."""
    cls = STREAMS[name]
    msg = _example(cls)
    assert equal(decode(cls, _repack(msg.encode(), lambda parts: None)), msg)


HEADER_TYPES = {
    "camera": 5,
    "trial": None,
    "frame": "3",
    "capture_ns": 1.5,
    "publish_ns": True,
    "last": 1,
}


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("key", sorted(HEADER_TYPES))
def test_wrong_header_types_are_rejected(name: str, key: str) -> None:
    cls = STREAMS[name]

    def edit(parts: list[Any]) -> None:
        parts[0][key] = HEADER_TYPES[key]

    with pytest.raises(SchemaError) as ei:
        decode(cls, _repack(_example(cls).encode(), edit))
    assert (ei.value.stream, ei.value.field) == (name, f"header.{key}")


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("key", ["schema", "version", "camera", "frame", "capture_ns", "last"])
def test_missing_header_keys_are_rejected(name: str, key: str) -> None:
    cls = STREAMS[name]

    def edit(parts: list[Any]) -> None:
        del parts[0][key]

    with pytest.raises(SchemaError) as ei:
        decode(cls, _repack(_example(cls).encode(), edit))
    assert (ei.value.stream, ei.value.field) == (name, f"header.{key}")


@pytest.mark.parametrize("name", ALL)
def test_other_stream_payload_is_rejected(name: str) -> None:
    cls = STREAMS[name]
    other = STREAMS[ALL[(ALL.index(name) + 1) % len(ALL)]]
    with pytest.raises(SchemaError) as ei:
        decode(cls, _example(other).encode())
    assert (ei.value.stream, ei.value.field) == (name, "header.schema")


def _array_cases(cls: type[Message]) -> list[tuple[str, str, Any]]:
    cases = []
    for f in _array_fields(cls):
        dtype, shape = f.metadata["array"]
        wrong = "<f4" if np.dtype(dtype).str != "<f4" else "<i4"
        cases.append((f.name, "dtype", wrong))
        cases.append((f.name, "ndim", [*([1] * len(shape)), 1]))
        fixed = [i for i, s in enumerate(shape) if s is not None]
        if fixed:
            shp = [1 if s is None else s for s in shape]
            shp[fixed[0]] += 1
            cases.append((f.name, "fixed", shp))
        cases.append((f.name, "bytes", [5, 7, 11][: len(shape)]))
        cases.append((f.name, "garbage", "not-a-dtype"))
        cases.append((f.name, "negative", [-1] * len(shape)))
        cases.append((f.name, "huge", [2**40] * len(shape)))
    return cases


@pytest.mark.parametrize(
    ("name", "field", "case", "value"),
    [(n, *c) for n in ALL for c in _array_cases(STREAMS[n])],
)
def test_wrong_array_descriptors_are_rejected(name: str, field: str, case: str, value: Any) -> None:
    cls = STREAMS[name]
    msg = _example(cls)

    def edit(parts: list[Any]) -> None:
        for d in parts[2]:
            if d[0] != field:
                continue
            if case == "dtype":
                # Same byte count under a different dtype: only the declared dtype catches it.
                d[1] = value
                n = np.dtype(value).itemsize
                d[2] = [len(parts[3 + parts[2].index(d)]) // n] + [1] * (len(d[2]) - 1)
            elif case == "garbage":
                d[1] = value
            else:
                d[2] = value

    with pytest.raises(SchemaError) as ei:
        decode(cls, _repack(msg.encode(), edit))
    assert (ei.value.stream, ei.value.field) == (name, field), ei.value


def _without_array(field: str) -> Any:
    """A ``_repack`` edit that removes one array (its descriptor and its bytes)."""

    def edit(parts: list[Any]) -> None:
        i = [d[0] for d in parts[2]].index(field)
        del parts[2][i]
        del parts[3 + i]

    return edit


@pytest.mark.parametrize("name", [n for n in ALL if _array_fields(STREAMS[n])])
def test_missing_array_is_rejected(name: str) -> None:
    cls = STREAMS[name]
    first = _array_fields(cls)[0].name
    with pytest.raises(SchemaError) as ei:
        decode(cls, _repack(_example(cls).encode(), _without_array(first)))
    assert (ei.value.stream, ei.value.field) == (name, first)


def _optional_arrays(cls: type[Message]) -> list[str]:
    return [f.name for f in _array_fields(cls) if f.metadata.get("optional")]


@pytest.mark.parametrize(
    ("name", "field"), [(n, f) for n in ALL for f in _optional_arrays(STREAMS[n])]
)
def test_an_array_added_after_the_version_reads_as_empty_when_absent(name: str, field: str) -> None:
    cls = STREAMS[name]
    msg = _example(cls)
    got = decode(cls, _repack(msg.encode(), _without_array(field)))
    dtype, shape = next(f for f in _array_fields(cls) if f.name == field).metadata["array"]
    a = getattr(got, field)
    assert a.dtype.str == dtype and a.shape == tuple(0 if n is None else n for n in shape)
    # the other fields are read as sent
    for f in _array_fields(cls):
        if f.name != field:
            np.testing.assert_array_equal(getattr(got, f.name), getattr(msg, f.name))


def test_labelled_carries_the_arrays_added_after_its_version() -> None:
    assert _optional_arrays(STREAMS["labelled"]) == ["spare_pixel", "spare_heel"]


def test_an_optional_array_needs_a_free_axis() -> None:
    with pytest.raises(ValueError, match="free axis"):
        array_field("float64", (20, 3), optional=True)


def _required_values(cls: type[Message]) -> list[str]:
    return [
        f.name
        for f in _value_fields(cls)
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]


@pytest.mark.parametrize(
    ("name", "field"), [(n, f) for n in ALL for f in _required_values(STREAMS[n])]
)
def test_missing_required_value_is_rejected(name: str, field: str) -> None:
    cls = STREAMS[name]
    msg = _example(cls)

    def edit(parts: list[Any]) -> None:
        del parts[1][field]

    with pytest.raises(SchemaError) as ei:
        decode(cls, _repack(msg.encode(), edit))
    assert (ei.value.stream, ei.value.field) == (name, field)


def _kinds(cls: type[Message]) -> list[tuple[str, tuple[type, ...]]]:
    return [(f.name, f.metadata["value"]) for f in _value_fields(cls)]


def _example_with_values(cls: type[Message]) -> Message:
    msg = _example(cls)
    return dataclasses.replace(msg, **{n: k[0]() for n, k in _kinds(cls)})


@pytest.mark.parametrize(("name", "field"), [(n, f) for n in ALL for f, _ in _kinds(STREAMS[n])])
def test_wrong_value_type_is_rejected(name: str, field: str) -> None:
    cls = STREAMS[name]
    kinds = dict(_kinds(cls))[field]
    wrong = [1, 2] if list not in kinds else "text"

    def edit(parts: list[Any]) -> None:
        parts[1][field] = wrong

    with pytest.raises(SchemaError) as ei:
        decode(cls, _repack(_example_with_values(cls).encode(), edit))
    assert (ei.value.stream, ei.value.field) == (name, field)


@pytest.mark.parametrize("name", ALL)
def test_encode_rejects_wrong_shape_naming_the_field(name: str) -> None:
    cls = STREAMS[name]
    for f in _array_fields(cls):
        shape = f.metadata["array"][1]
        msg = dataclasses.replace(_example(cls), **{f.name: np.ones((1,) * (len(shape) + 1))})
        with pytest.raises(SchemaError) as ei:
            msg.encode()
        assert (ei.value.stream, ei.value.field) == (name, f.name)


# ----------------------------------------------------------------------- JSON Schema files


@pytest.mark.parametrize("name", ALL)
def test_json_schema_files_are_in_sync(name: str) -> None:
    """schemas/<stream>.json is what ``python -m gaitflow.schemas`` generates now."""
    path = Path(schemas_pkg.__file__).parent / f"{name}.json"
    assert path.exists(), f"{path} missing: run python -m gaitflow.schemas"
    on_disk = json.loads(path.read_text())
    assert on_disk == json_schema(STREAMS[name]), f"{path} is stale: run python -m gaitflow.schemas"


def test_no_stray_json_schema_files() -> None:
    here = Path(schemas_pkg.__file__).parent
    assert {p.stem for p in here.glob("*.json")} == set(STREAMS)


def _empty_blobs() -> bytes:
    from gaitflow.schemas import Blobs

    z = np.zeros
    return Blobs(
        header=Blobs.make_header("cam0", "walk-01", 0, 0),
        centroid=z((0, 2)),
        marker_radius=z(0),
        region_radius=z(0),
        mean_ir=z(0),
        area=z(0, "i4"),
        threshold=1.0,
    ).encode()


@pytest.mark.parametrize(
    "shape",
    [[2**32, 2**32], [2**62, 4], [2**63, 0], [0, 2**64 - 1], [True, 2], "12", [1.5, 2], None],
)
def test_hostile_shapes_on_empty_arrays_are_rejected(shape: Any) -> None:
    """Shapes whose element count overflows int64 (or are not int lists) on 0 bytes."""

    def edit(parts: list[Any]) -> None:
        parts[2][0][2] = shape

    with pytest.raises(SchemaError) as ei:
        decode(STREAMS["blobs"], _repack(_empty_blobs(), edit))
    assert (ei.value.stream, ei.value.field) == ("blobs", "centroid")


@pytest.mark.parametrize(
    "dtype", ["|O8", "O", "a", "V0", "<U3", "<c16", "float64", ["<f8"], {"a": 1}, None, 8]
)
def test_unsupported_dtypes_are_rejected(dtype: Any) -> None:
    def edit(parts: list[Any]) -> None:
        parts[2][0][1] = dtype

    with pytest.raises(SchemaError) as ei:
        decode(STREAMS["blobs"], _repack(_empty_blobs(), edit))
    assert (ei.value.stream, ei.value.field) == ("blobs", "centroid")
