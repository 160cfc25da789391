"""Input conversion for the compiled module: checked numpy arrays of the types the library uses."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

_U32_MAX = 2**32 - 1


def float_array(obj: Any, name: str, ndim: int) -> np.ndarray:
    """A C-contiguous float64 array of ``ndim`` dimensions (a copy only when needed)."""
    a = np.asarray(obj)
    if a.dtype.kind not in "fiu" and not (a.size == 0 and a.dtype.kind in "O"):
        raise TypeError(f"{name}: expected real numbers, got an array of {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.ndim != ndim:
        if a.size == 0 and ndim == 2:
            return a.reshape(0, 0)
        raise ValueError(f"{name}: expected {ndim} dimension(s), got shape {a.shape}")
    return a


def index_array(obj: Any, name: str, ndim: int) -> np.ndarray:
    """A C-contiguous uint32 array; refuses non-integers, negatives and values above 2**32 - 1
    instead of letting numpy wrap them around."""
    a = np.asarray(obj)
    if a.size == 0:
        a = a.astype(np.uint32)
    if a.dtype.kind not in "iu":
        raise TypeError(f"{name}: expected integers, got an array of {a.dtype}")
    if a.size and (int(a.min()) < 0 or int(a.max()) > _U32_MAX):
        raise ValueError(f"{name}: indices must lie in 0..2**32-1, got {int(a.min())}..{int(a.max())}")
    a = np.ascontiguousarray(a, dtype=np.uint32)
    if a.ndim != ndim:
        raise ValueError(f"{name}: expected {ndim} dimension(s), got shape {a.shape}")
    return a


def to_json(obj: Any, name: str) -> str:
    """JSON text of a Python object (``extras``, extension payloads); NaN and infinity are refused
    because JSON cannot carry them."""
    try:
        return json.dumps(obj, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name}: not representable as JSON: {e}") from None


from_json = json.loads


def npy_view(buf: np.ndarray) -> np.ndarray:
    """The structured array stored in an in-memory NPY file (a uint8 array), as a view of it."""
    import io

    head = io.BytesIO(buf[:65536].tobytes())
    if np.lib.format.read_magic(head) != (1, 0):
        raise ValueError("expected NPY version 1.0")
    shape, fortran, dtype = np.lib.format.read_array_header_1_0(head)
    if fortran:
        raise ValueError("unexpected Fortran-ordered NPY data")
    data = buf[head.tell():]
    out = data.view(dtype)
    if out.shape != (shape[0] if shape else 1,):
        raise ValueError("NPY data length does not match its header")
    return out
