"""NumPy arrays in msgpack, byte-compatible with openpi's ``openpi_client.msgpack_numpy``, without pickle.

An array travels as the map ``{b"__ndarray__": True, b"data": <C-order bytes>, b"dtype": <dtype.str>,
b"shape": [dims]}`` and a NumPy scalar as ``{b"__npgeneric__": True, b"data": <item>, b"dtype": <dtype.str>}``,
the two forms openpi's client and server exchange. Only booleans, integers and floats cross the wire: object,
structured (void), complex and string dtypes are refused both ways, so a message can never ask NumPy to build
Python objects.

Decoding treats the message as hostile: an array header is checked (dtype whitelist, shape of non-negative
ints, data length = elements x itemsize) before a zero-copy, read-only array is built on the message's
bytes, and the number of maps and lists is capped, so a small message cannot expand into millions of Python
containers. Every problem raises :class:`DecodeError` naming it.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

NDARRAY, NPGENERIC = b"__ndarray__", b"__npgeneric__"
ALLOWED_KINDS = "biuf"  # bool, signed and unsigned integers, floats
MAX_DIMS = 32
MAX_DTYPE_CHARS = 8  # "<f8", "|u1", "float32"...; a longer string is no dtype this protocol uses
DEFAULT_MAX_CONTAINERS = 100_000


class DecodeError(ValueError):
    """A message is not msgpack, or holds an array this protocol refuses; the text says which and why."""


def _check_dtype(dtype: np.dtype, where: str) -> None:
    if dtype.kind not in ALLOWED_KINDS or dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None:
        raise DecodeError(f"{where}: dtype {dtype.str!r} refused (only bool, integer and float arrays cross the wire)")


def _pack_default(obj: Any) -> Any:
    """msgpack's hook for types it does not know: NumPy arrays and scalars, as openpi encodes them."""
    if isinstance(obj, (np.ndarray, np.generic)) and (obj.dtype.kind not in ALLOWED_KINDS or obj.dtype.fields):
        raise TypeError(f"cannot send a NumPy {obj.dtype} value: only bool, integer and float arrays cross the wire")
    if isinstance(obj, np.ndarray):
        return {NDARRAY: True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {NPGENERIC: True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send a {type(obj).__name__} over msgpack")


def packb(obj: Any) -> bytes:
    """Serialize dicts, lists, str, bytes, numbers, None and NumPy arrays/scalars."""
    return msgpack.packb(obj, default=_pack_default, use_bin_type=True)


def _dtype_of(header: dict, where: str) -> np.dtype:
    name = header.get(b"dtype")
    if not isinstance(name, str) or not name or len(name) > MAX_DTYPE_CHARS:
        raise DecodeError(f"{where}: 'dtype' must be a short dtype string such as '<f4', got {name!r:.40}")
    try:
        dtype = np.dtype(name)
    except (TypeError, ValueError):
        raise DecodeError(f"{where}: unknown dtype {name!r}") from None
    _check_dtype(dtype, where)
    return dtype


def _array(header: dict) -> np.ndarray:
    dtype = _dtype_of(header, "array")
    data, shape = header.get(b"data"), header.get(b"shape")
    if not isinstance(data, bytes):
        raise DecodeError(f"array: 'data' must be bytes, got {type(data).__name__}")
    if (not isinstance(shape, (list, tuple)) or len(shape) > MAX_DIMS
            or not all(type(d) is int and d >= 0 for d in shape)):
        raise DecodeError(f"array: 'shape' must be a list of at most {MAX_DIMS} non-negative ints, got {shape!r:.80}")
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise DecodeError(f"array: shape {tuple(shape)} of {dtype.str} needs {expected} bytes of data, got {len(data)}")
    return np.ndarray(shape=tuple(shape), dtype=dtype, buffer=data)


def _generic(header: dict) -> np.generic:
    dtype = _dtype_of(header, "scalar")
    data = header.get(b"data")
    if not isinstance(data, (bool, int, float)):
        raise DecodeError(f"scalar: 'data' must be a number, got {type(data).__name__}")
    try:
        return dtype.type(data)
    except (OverflowError, ValueError, TypeError) as e:
        raise DecodeError(f"scalar: {data!r} is not a {dtype.str} value ({e})") from None


class _Hooks:
    """msgpack's per-map and per-list callbacks: arrays and scalars, and the container budget."""

    def __init__(self, max_containers: int):
        self.left = max_containers

    def _spend(self) -> None:
        self.left -= 1
        if self.left < 0:
            raise DecodeError("message nests too many maps and lists")

    def object_hook(self, obj: dict) -> Any:
        self._spend()
        if NDARRAY in obj:
            return _array(obj)
        if NPGENERIC in obj:
            return _generic(obj)
        return obj

    def list_hook(self, items: list) -> list:
        self._spend()
        return items


def _refuse_ext(code: int, data: bytes) -> Any:
    raise DecodeError(f"msgpack extension type {code} refused")


def unpackb(data: bytes, max_containers: int = DEFAULT_MAX_CONTAINERS) -> Any:
    """The object in ``data``, arrays as read-only NumPy arrays on its bytes; :class:`DecodeError` for
    anything that is not a well-formed message of this protocol."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise DecodeError(f"a message is bytes, got {type(data).__name__}")
    hooks = _Hooks(max_containers)
    try:
        return msgpack.unpackb(data, object_hook=hooks.object_hook, list_hook=hooks.list_hook, ext_hook=_refuse_ext,
                               raw=False)
    except DecodeError:
        raise
    except Exception as e:  # noqa: BLE001 - msgpack raises many types (ExtraData, FormatError, ValueError, ...)
        raise DecodeError(f"not a valid msgpack message ({type(e).__name__}: {e})") from None
