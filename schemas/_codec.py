"""Message codec shared by every stream schema.

A message is a frozen dataclass: a :class:`Header` plus the stream's own fields. A field is
either an array, declared with :func:`array_field` (dtype and shape, ``None`` = any length
along that axis), or a plain msgpack value, declared with :func:`value_field`.

Wire format: one msgpack array ``[header, fields, descriptors, bin_0, bin_1, ...]`` where
``descriptors`` is ``[[name, dtype, shape], ...]`` and each ``bin_i`` holds the raw C-order
bytes of array i. The arrays are therefore never msgpack lists, any msgpack reader can parse
a message, and :func:`decode` reads the arrays straight out of the payload without copying
(the arrays it returns are read-only views).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import struct
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np

from gaitflow.errors import SchemaError, SchemaVersionError

HEADER_KEYS = ("schema", "version", "camera", "trial", "frame", "capture_ns", "publish_ns", "last")
_BIN32 = 0xC6
_DTYPE_STR = re.compile(r"[<>|][biuf][1248]")
_BIN_LEN = {0xC4: ">B", 0xC5: ">H", _BIN32: ">I"}
_INT_TYPES = (int,)
# Validated array layouts: (class, descriptor bytes) -> ((name, dtype, shape, nbytes), ...).
_PLANS: dict[tuple[type, bytes], tuple[tuple[str, np.dtype, tuple[int, ...], int], ...]] = {}
_MAX_PLANS = 512


@dataclass(frozen=True)
class Header:
    """The versioned header every message carries.

    ``frame`` is the camera frame index within the trial; ``capture_ns`` is the sensor
    capture time and ``publish_ns`` the wall-clock time the message was put on the bus
    (both int64 ns). ``last`` marks the final frame of a trial, so stateful stages can
    close it.
    """

    schema: str
    version: int
    camera: str
    trial: str
    frame: int
    capture_ns: int
    publish_ns: int = 0
    last: bool = False

    def to_map(self) -> dict[str, Any]:
        # Not dataclasses.asdict: its deep copy costs ~50 us per message, on every encode.
        return {k: getattr(self, k) for k in HEADER_KEYS}


def array_field(
    dtype: str, shape: tuple[int | None, ...], meaning: str = "", optional: bool = False
) -> Any:
    """Declare an array field: numpy dtype name and shape (None = free axis length).

    ``optional``: an array added to a stream after its version was published. Messages
    without it (older recordings) still decode; the field is then empty (length 0 along
    every free axis), so it needs a free axis.
    """
    meta = {"array": (np.dtype(dtype).str, tuple(shape)), "meaning": meaning}
    if not optional:
        return field(metadata=meta)
    if None not in shape:
        raise ValueError(f"optional array field needs a free axis, not shape {shape!r}")
    empty = tuple(0 if n is None else n for n in shape)
    return field(
        default_factory=lambda: np.zeros(empty, dtype=dtype),
        metadata={**meta, "optional": True},
    )


def value_field(
    kind: type | tuple[type, ...], default: Any = dataclasses.MISSING, meaning: str = ""
) -> Any:
    """Declare a plain msgpack field (int, float, str, bool, list, dict or None)."""
    meta = {"value": kind if isinstance(kind, tuple) else (kind,), "meaning": meaning}
    if default is dataclasses.MISSING:
        return field(metadata=meta)
    if isinstance(default, list | dict):
        return field(default_factory=lambda d=default: type(d)(d), metadata=meta)
    return field(default=default, metadata=meta)


M = TypeVar("M", bound="Message")


@dataclass(frozen=True, eq=False)
class Message:
    """Base class of every stream message. Subclasses set STREAM and VERSION."""

    STREAM: ClassVar[str] = ""
    VERSION: ClassVar[int] = 0
    DOC: ClassVar[str] = ""

    header: Header

    @classmethod
    def make_header(
        cls,
        camera: str,
        trial: str,
        frame: int,
        capture_ns: int,
        last: bool = False,
    ) -> Header:
        """A header for this stream with the current schema name and version."""
        return Header(cls.STREAM, cls.VERSION, camera, trial, int(frame), int(capture_ns), 0, last)

    @classmethod
    def follow(cls: type[M], upstream: Header, **fields: Any) -> M:
        """A message of this stream for the same camera, trial and frame as ``upstream``."""
        hdr = Header(
            cls.STREAM,
            cls.VERSION,
            upstream.camera,
            upstream.trial,
            upstream.frame,
            upstream.capture_ns,
            0,
            upstream.last,
        )
        return cls(header=hdr, **fields)

    def encode(self, publish_ns: int | None = None) -> bytes:
        return encode(self, publish_ns)

    def encode_into(self, out: bytearray, publish_ns: int | None = None) -> bytearray:
        return encode_into(self, out, publish_ns)


@functools.cache
def _fields(cls: type[Message]) -> tuple[dataclasses.Field[Any], ...]:
    # Cached: dataclasses.fields costs ~10 us, and encode/decode run per frame per stage.
    return tuple(f for f in dataclasses.fields(cls) if f.name != "header")


def _bin_header(n: int) -> bytes:
    return struct.pack(">BI", _BIN32, n)


def encode(msg: Message, publish_ns: int | None = None) -> bytes:
    """Encode ``msg``; ``publish_ns`` (default: now) is stamped into the header."""
    return b"".join(_encode_parts(msg, publish_ns))


def encode_into(msg: Message, out: bytearray, publish_ns: int | None = None) -> bytearray:
    """Encode ``msg`` into ``out`` (resized to the payload's length) and return ``out``.

    The same bytes as :func:`encode`, written into a buffer the caller reuses from frame to
    frame: a fresh 868 KB ``bytes`` per raw frame costs page faults (the allocator maps and
    unmaps it each time), a warm buffer only the copy. The caller must not reuse ``out``
    while a consumer may still read it (the Zenoh publisher copies it before returning).
    """
    parts = _encode_parts(msg, publish_ns)
    n = sum(len(p) for p in parts)  # parts are bytes or 1-byte-format memoryviews
    if len(out) > n:
        del out[n:]
    elif len(out) < n:
        out.extend(bytes(n - len(out)))
    with memoryview(out) as mv:
        o = 0
        for part in parts:
            k = len(part)
            mv[o : o + k] = part
            o += k
    return out


def _encode_parts(msg: Message, publish_ns: int | None) -> list[Any]:
    """The payload of ``msg`` as a list of byte strings and array views, in wire order."""
    cls = type(msg)
    hdr = msg.header.to_map()
    hdr["schema"], hdr["version"] = cls.STREAM, cls.VERSION
    hdr["publish_ns"] = time.time_ns() if publish_ns is None else int(publish_ns)
    values: dict[str, Any] = {}
    descr: list[list[Any]] = []
    blobs: list[Any] = []
    for f in _fields(cls):
        v = getattr(msg, f.name)
        if "array" in f.metadata:
            dtype, shape = f.metadata["array"]
            a = np.asarray(v)
            if a.dtype.str != dtype:
                if a.size == 0 or np.can_cast(a.dtype, dtype, casting="same_kind"):
                    a = a.astype(dtype)
                else:
                    raise SchemaError(cls.STREAM, f.name, f"dtype {a.dtype} is not {dtype}")
            _check_shape(cls.STREAM, f.name, a.shape, shape)
            a = np.ascontiguousarray(a)
            descr.append([f.name, dtype, list(a.shape)])
            blobs.append(_bin_header(a.nbytes))
            blobs.append(memoryview(a).cast("B") if a.nbytes else b"")
        else:
            values[f.name] = _check_value(cls.STREAM, f.name, v, f.metadata["value"])
    head = msgpack.packb(hdr, use_bin_type=True)
    head += msgpack.packb(values, use_bin_type=True)
    head += msgpack.packb(descr, use_bin_type=True)
    n = 3 + len(descr)
    prefix = bytes([0x90 | n]) if n < 16 else struct.pack(">BH", 0xDC, n)
    return [prefix, head, *blobs]


def _check_shape(stream: str, name: str, got: tuple[int, ...], want: tuple[Any, ...]) -> None:
    if got == want:
        return  # the common case of a fully fixed shape, without the loop below
    if len(got) != len(want) or any(
        w is not None and g != w for g, w in zip(got, want, strict=False)
    ):
        raise SchemaError(stream, name, f"shape {tuple(got)} does not match {tuple(want)}")


def _check_value(stream: str, name: str, v: Any, kinds: tuple[type, ...]) -> Any:
    if isinstance(v, np.generic):
        v = v.item()
    if float in kinds and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if isinstance(v, bool) and bool not in kinds:
        raise SchemaError(stream, name, f"value {v!r} is not {'/'.join(k.__name__ for k in kinds)}")
    if not isinstance(v, kinds):
        raise SchemaError(stream, name, f"value {v!r} is not {'/'.join(k.__name__ for k in kinds)}")
    return v


def peek_header(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """The header map of a payload, without decoding the rest."""
    reader = _Reader(payload, "<unknown>")
    hdr = reader.next("header")
    if not isinstance(hdr, dict):
        raise SchemaError("<unknown>", "header", "is not a map")
    return hdr


class _Reader:
    """Incremental msgpack reader over a payload.

    It feeds a prefix only: the meta part is small, and the arrays behind it need not be
    copied into the unpacker.
    """

    def __init__(self, payload: Any, stream: str) -> None:
        self.stream = stream
        self.buf = payload if isinstance(payload, bytes) else memoryview(payload).cast("B")
        self.unpacker = msgpack.Unpacker(raw=False, max_buffer_size=max(len(self.buf), 1 << 20))
        self.fed = 0
        self._feed(1 << 12)  # the meta part is small; arrays are never fed
        try:
            self.parts = self.unpacker.read_array_header()
        except msgpack.OutOfData as exc:
            raise SchemaError(stream, "<payload>", "empty or truncated payload") from exc
        except (msgpack.UnpackValueError, msgpack.FormatError, ValueError) as exc:
            raise SchemaError(stream, "<payload>", f"not a gaitflow message: {exc}") from exc
        if self.parts < 3:
            raise SchemaError(stream, "<payload>", f"expected at least 3 parts, got {self.parts}")

    def _feed(self, upto: int) -> None:
        nxt = min(len(self.buf), upto)
        self.unpacker.feed(self.buf[self.fed : nxt])
        self.fed = nxt

    def next(self, part: str) -> Any:
        while True:
            try:
                return self.unpacker.unpack()
            except msgpack.OutOfData as exc:
                if self.fed >= len(self.buf):
                    raise SchemaError(self.stream, part, "truncated payload") from exc
                self._feed(self.fed * 4)
            except (msgpack.UnpackValueError, msgpack.FormatError, ValueError) as exc:
                raise SchemaError(self.stream, part, f"malformed msgpack: {exc}") from exc


def _bin_at(buf: memoryview | bytes, offset: int, stream: str, name: str) -> tuple[int, int]:
    """(length, offset of the bytes) of the msgpack bin at ``offset``; checked to fit ``buf``.

    We write bin32; other msgpack writers pick the smallest bin type, accept those too.
    """
    lenfmt = _BIN_LEN.get(buf[offset]) if offset < len(buf) else None
    if lenfmt is None or offset + 1 + struct.calcsize(lenfmt) > len(buf):
        raise SchemaError(stream, name, "array bytes missing or truncated")
    (nbytes,) = struct.unpack_from(lenfmt, buf, offset + 1)
    offset += 1 + struct.calcsize(lenfmt)
    if offset + nbytes > len(buf):
        raise SchemaError(stream, name, "array bytes truncated")
    return nbytes, offset


def decode(cls: type[M], payload: bytes | bytearray | memoryview) -> M:
    """Decode a payload of stream ``cls``; raise SchemaError naming the field at fault."""
    stream = cls.STREAM
    reader = _Reader(payload, stream)
    buf, n = reader.buf, reader.parts
    hdr = reader.next("header")
    values = reader.next("fields")
    start = reader.unpacker.tell()
    descr = reader.next("descriptors")
    offset = reader.unpacker.tell()
    if not isinstance(hdr, dict):
        raise SchemaError(stream, "header", "is not a map")
    for key in HEADER_KEYS:
        if key not in hdr:
            raise SchemaError(stream, f"header.{key}", "missing")
    if hdr["schema"] != stream:
        raise SchemaError(stream, "header.schema", f"got {hdr['schema']!r}, expected {stream!r}")
    if hdr["version"] != cls.VERSION:
        raise SchemaVersionError(
            stream,
            "header.version",
            f"version {hdr['version']!r} is not supported (expected {cls.VERSION})",
        )
    for key, kind in (
        ("camera", str),
        ("trial", str),
        ("frame", int),
        ("capture_ns", int),
        ("publish_ns", int),
        ("last", bool),
    ):
        v = hdr[key]
        if not isinstance(v, kind) or (kind is int and isinstance(v, bool)):
            raise SchemaError(stream, f"header.{key}", f"value {v!r} is not {kind.__name__}")
    header = Header(**{k: hdr[k] for k in HEADER_KEYS})
    if not isinstance(values, dict):
        raise SchemaError(stream, "fields", "is not a map")
    if not isinstance(descr, list) or len(descr) != n - 3:
        raise SchemaError(stream, "descriptors", "do not match the number of arrays")
    # Descriptor sections already validated for this class (same bytes) skip the checks that
    # depend on them alone; what depends on the payload (bin headers, lengths) is still
    # checked below, in the same order, so errors are the same with or without the cache.
    plan_key = (cls, bytes(buf[start:offset]))
    plan = _PLANS.get(plan_key)
    arrays: dict[str, np.ndarray] = {}
    if plan is not None:
        for name, dt, shp, want_nbytes in plan:
            nbytes, offset = _bin_at(buf, offset, stream, name)
            if nbytes != want_nbytes:
                raise SchemaError(stream, name, f"{nbytes} bytes do not hold {dt.str} {list(shp)}")
            arrays[name] = np.frombuffer(
                buf, dtype=dt, count=nbytes // dt.itemsize, offset=offset
            ).reshape(shp)
            offset += nbytes
        descr = []  # the loop below has nothing left to do
    new_plan: list[tuple[str, np.dtype, tuple[int, ...], int]] = []
    for d in descr:
        if not (isinstance(d, list) and len(d) == 3 and isinstance(d[0], str)):
            raise SchemaError(stream, "descriptors", f"malformed descriptor {d!r}")
        name, dtype, shape = d
        nbytes, offset = _bin_at(buf, offset, stream, name)
        # Only plain numeric dtypes in numpy's ``dtype.str`` form (what encode writes), and
        # the size check in Python ints: np.prod would overflow on hostile shapes.
        if not (isinstance(dtype, str) and _DTYPE_STR.fullmatch(dtype)):
            raise SchemaError(stream, name, f"unsupported dtype {dtype!r}")
        if not (
            isinstance(shape, list)
            and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)
        ):
            raise SchemaError(stream, name, f"bad shape {shape!r}")
        try:
            dt = np.dtype(dtype)
        except TypeError as exc:
            raise SchemaError(stream, name, f"unsupported dtype {dtype!r}") from exc
        shp = tuple(shape)
        if math.prod(shp) * dt.itemsize != nbytes:
            raise SchemaError(stream, name, f"{nbytes} bytes do not hold {dtype} {list(shp)}")
        try:
            arrays[name] = np.frombuffer(
                buf, dtype=dt, count=nbytes // dt.itemsize, offset=offset
            ).reshape(shp)
        except ValueError as exc:  # e.g. a zero-size shape with an axis beyond numpy's limit
            raise SchemaError(stream, name, f"bad shape {list(shp)}: {exc}") from exc
        new_plan.append((name, dt, shp, nbytes))
        offset += nbytes
    kwargs: dict[str, Any] = {}
    for f in _fields(cls):
        if "array" in f.metadata:
            if f.name not in arrays:
                if f.metadata.get("optional"):
                    continue  # added later: an older message reads as empty
                raise SchemaError(stream, f.name, "missing array")
            a = arrays[f.name]
            if plan is None:
                want_dtype, want_shape = f.metadata["array"]
                if a.dtype.str != want_dtype:
                    raise SchemaError(stream, f.name, f"dtype {a.dtype.str} is not {want_dtype}")
                _check_shape(stream, f.name, a.shape, want_shape)
            kwargs[f.name] = a
        else:
            if f.name not in values:
                if (
                    f.default is not dataclasses.MISSING
                    or f.default_factory is not dataclasses.MISSING
                ):
                    continue  # fields added later with a default stay readable
                raise SchemaError(stream, f.name, "missing field")
            kwargs[f.name] = _check_value(stream, f.name, values[f.name], f.metadata["value"])
    if plan is None:
        # Only a descriptor section that decoded completely is remembered.
        if len(_PLANS) >= _MAX_PLANS:
            _PLANS.clear()  # variable-length arrays give many layouts: keep it bounded
        _PLANS[plan_key] = tuple(new_plan)
    return cls(header=header, **kwargs)


def messages_equal(a: Message, b: Message) -> bool:
    """True when two messages carry the same header and values (NaN equals NaN)."""
    if type(a) is not type(b):
        return False
    if dataclasses.replace(a.header, publish_ns=0) != dataclasses.replace(b.header, publish_ns=0):
        return False
    for f in _fields(type(a)):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if "array" in f.metadata:
            x, y = np.asarray(x), np.asarray(y)
            if x.shape != y.shape or x.dtype != y.dtype:
                return False
            if x.dtype.kind in "fc":
                if not np.array_equal(x, y, equal_nan=True):
                    return False
            elif not np.array_equal(x, y):
                return False
        elif x != y and not (isinstance(x, float) and isinstance(y, float) and x != x and y != y):
            return False
    return True


def json_schema(cls: type[Message]) -> dict[str, Any]:
    """A JSON Schema (draft 2020-12) of the decoded message, with array layouts."""
    props: dict[str, Any] = {}
    arrays: dict[str, Any] = {}
    for f in _fields(cls):
        if "array" in f.metadata:
            dtype, shape = f.metadata["array"]
            arrays[f.name] = {
                "dtype": dtype,
                "shape": [s if s is not None else "*" for s in shape],
                "description": f.metadata.get("meaning", ""),
                **({"optional": True} if f.metadata.get("optional") else {}),
            }
        else:
            names = {
                int: "integer",
                float: "number",
                str: "string",
                bool: "boolean",
                list: "array",
                dict: "object",
                type(None): "null",
            }
            props[f.name] = {
                "type": [names[k] for k in f.metadata["value"]],
                "description": f.metadata.get("meaning", ""),
            }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"gaitflow/{cls.STREAM}/v{cls.VERSION}",
        "title": f"gaitflow {cls.STREAM} message, version {cls.VERSION}",
        "description": (cls.DOC or cls.__doc__ or "").strip(),
        "type": "array",
        "x-gaitflow-encoding": "msgpack [header, fields, descriptors, bin...]; raw C-order arrays",
        "prefixItems": [
            {
                "type": "object",
                "required": list(HEADER_KEYS),
                "properties": {
                    "schema": {"const": cls.STREAM},
                    "version": {"const": cls.VERSION},
                    "camera": {"type": "string"},
                    "trial": {"type": "string"},
                    "frame": {"type": "integer"},
                    "capture_ns": {"type": "integer"},
                    "publish_ns": {"type": "integer"},
                    "last": {"type": "boolean"},
                },
            },
            {"type": "object", "properties": props},
            {
                "type": "array",
                "description": "[[name, dtype, shape], ...] of the arrays that follow",
            },
        ],
        "x-gaitflow-arrays": arrays,
    }


REGISTRY: dict[str, type[Message]] = {}


def register(cls: type[M]) -> type[M]:
    """Class decorator: make a message class known by its stream name."""
    if cls.STREAM in REGISTRY and REGISTRY[cls.STREAM] is not cls:
        raise ValueError(f"stream {cls.STREAM!r} registered twice")
    REGISTRY[cls.STREAM] = cls
    return cls


def decode_any(
    payload: bytes | bytearray | memoryview, registry: Mapping[str, type[Message]] | None = None
) -> Message:
    """Decode a payload of any registered stream, dispatching on its header."""
    reg = REGISTRY if registry is None else registry
    hdr = peek_header(payload)
    name = hdr.get("schema")
    if name not in reg:
        raise SchemaError(str(name), "header.schema", "unknown stream")
    return decode(reg[name], payload)
