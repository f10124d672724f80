"""The policy server's wire format: msgpack maps, numpy arrays as typed byte maps, checked against a schema.

Torch-free (numpy and msgpack only): the robot-side client imports it. Nothing is ever unpickled: an array travels
as {"__ndarray__": True, "dtype": "<f4", "shape": [...], "data": bytes} with a dtype from a short list, and a
message is a map whose fields are checked (type, dtype, shape, size) before anything acts on it.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

PROTOCOL = 1
MAX_MESSAGE_BYTES = 16 << 20  # one observation of a few 224 px frames is under 2 MiB; a larger frame is refused
MAX_SIDE = 1024  # pixels, per image side
DTYPES = {"|u1": np.uint8, "<f4": np.float32, "<f8": np.float64, "<i4": np.int32, "<i8": np.int64, "|b1": np.bool_}


class WireError(ValueError):
    """A message that does not follow the protocol: the server answers it with an error and goes on."""


def pack_array(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    dtype = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    if dtype.str not in DTYPES:
        raise WireError(f"dtype {a.dtype} cannot be sent (one of {', '.join(DTYPES)})")
    return {"__ndarray__": True, "dtype": dtype.str, "shape": list(a.shape), "data": a.astype(dtype).tobytes()}


def _unpack_array(m: dict) -> np.ndarray:
    dtype, shape, data = m.get("dtype"), m.get("shape"), m.get("data")
    if dtype not in DTYPES:
        raise WireError(f"array dtype {dtype!r} is not one of {', '.join(DTYPES)}")
    if (not isinstance(shape, list) or len(shape) > 4
            or not all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= 1 << 24 for n in shape)):
        raise WireError(f"array shape {shape!r} is not a list of at most 4 sizes")
    if not isinstance(data, bytes):
        raise WireError("array data is not bytes")
    want = math.prod(shape) * np.dtype(DTYPES[dtype]).itemsize
    if len(data) != want:
        raise WireError(f"array of shape {shape} and dtype {dtype} needs {want} bytes, got {len(data)}")
    return np.frombuffer(data, DTYPES[dtype]).reshape(shape)


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return pack_array(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot send {type(obj).__name__}")


def _decode(m: dict) -> Any:
    return _unpack_array(m) if m.get("__ndarray__") is True else m


def dumps(doc: dict) -> bytes:
    return msgpack.packb(doc, default=_encode, use_bin_type=True)


def loads(data: bytes | str) -> dict:
    """A message map, or WireError (never a traceback) for anything else: text frames, truncated or malformed
    msgpack, oversized containers, arrays whose bytes do not match their declared shape."""
    if not isinstance(data, bytes):
        raise WireError("a text frame: messages are binary msgpack")
    if len(data) > MAX_MESSAGE_BYTES:
        raise WireError(f"message of {len(data)} bytes is over the limit of {MAX_MESSAGE_BYTES}")
    try:
        doc = msgpack.unpackb(data, raw=False, object_hook=_decode, strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES,
                              max_str_len=1 << 16, max_array_len=1 << 12, max_map_len=64)
    except WireError:
        raise
    except (msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, ValueError, TypeError, UnicodeDecodeError,
            RecursionError) as exc:
        raise WireError(f"not a msgpack message ({type(exc).__name__}: {str(exc)[:80]})") from None
    if not isinstance(doc, dict):
        raise WireError(f"a message is a map, got {type(doc).__name__}")
    return doc


def field(doc: dict, name: str, kind: type | tuple, required: bool = True) -> Any:
    value = doc.get(name)
    if value is None:
        if required:
            raise WireError(f"missing field {name!r}")
        return None
    if isinstance(value, bool) and kind in (int, float, (int, float)):
        raise WireError(f"field {name!r} is a bool, not a number")
    if not isinstance(value, kind):
        raise WireError(f"field {name!r} is {type(value).__name__}, not {getattr(kind, '__name__', kind)}")
    return value


def array(doc: dict, name: str, shape: tuple, dtypes: tuple, required: bool = True) -> np.ndarray | None:
    """A field that must be an array of `shape` (None: any size on that axis) and one of `dtypes`."""
    a = field(doc, name, np.ndarray, required)
    if a is None:
        return None
    if a.dtype not in [np.dtype(d) for d in dtypes]:
        raise WireError(f"field {name!r} has dtype {a.dtype}, not {' or '.join(np.dtype(d).name for d in dtypes)}")
    if a.ndim != len(shape) or any(w is not None and n != w for n, w in zip(a.shape, shape, strict=True)):
        want = "(" + ", ".join("any" if w is None else str(w) for w in shape) + ")"
        raise WireError(f"field {name!r} has shape {a.shape}, not {want}")
    if a.dtype.kind == "f" and name not in ("depth",) and not np.isfinite(a).all():
        raise WireError(f"field {name!r} holds NaN or infinite values")
    return a
