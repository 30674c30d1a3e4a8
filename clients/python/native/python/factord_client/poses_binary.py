"""Binary estimates, as published on ``<p>/<session>/bin/poses`` (the layout is
``proto/v1/poses-binary.md``): the ``estimate`` events of ``out/poses`` without JSON, about 40
bytes an SE(2) pose against about 100, read straight into numpy arrays.

A ``lagged`` marker on that key is JSON, as on every other key: :func:`decode_event` tells the
two apart by their first bytes (``FDPB`` or ``{``).
"""

from __future__ import annotations

import json
import struct
from typing import Any, Dict, List

import numpy as np

from .batch import EstimateArray

MAGIC = b"FDPB"
VERSION = 1
_HEADER = struct.Struct("<4sIQI")  # magic, version, sequence, groups
_GROUP_TAIL = struct.Struct("<BI")  # dimension, count (after the kind's length and name)


class PosesBinaryError(ValueError):
    """The bytes are not a binary estimate this client can read."""


def decode_poses(payload: bytes, session: str = "") -> Dict[str, Any]:
    """A binary estimate as ``{"type": "estimate", "sequence": n, "session": session,
    "arrays": {kind: EstimateArray}}``: per kind, its variables sorted by key, with ``changed``
    (the sequence that last changed each) and ``stamps`` all NaN (stamps are not sent in
    binary; the JSON topic and the estimate route carry them)."""
    view = memoryview(payload)
    if len(view) < _HEADER.size or bytes(view[:4]) != MAGIC:
        raise PosesBinaryError("not a binary estimate: it does not start with FDPB")
    _, version, sequence, groups = _HEADER.unpack_from(view, 0)
    if version != VERSION:
        raise PosesBinaryError(f"binary estimate version {version} is not known "
                               f"(this client reads version {VERSION})")
    at = _HEADER.size
    parts: Dict[str, List[np.ndarray]] = {}
    for group in range(groups):
        if at + 1 > len(view):
            raise PosesBinaryError(f"cut short at byte {at}: group {group} is missing")
        length = view[at]
        at += 1
        kind_bytes = bytes(view[at:at + length])
        at += length
        if len(kind_bytes) != length or at + _GROUP_TAIL.size > len(view):
            raise PosesBinaryError(f"cut short at byte {at}: group {group}'s header")
        try:
            kind = kind_bytes.decode("ascii")
        except UnicodeDecodeError:
            raise PosesBinaryError(f"group {group} names a kind that is not ASCII") from None
        dimension, count = _GROUP_TAIL.unpack_from(view, at)
        at += _GROUP_TAIL.size
        record = np.dtype([("key", "<u8"), ("changed", "<u8"), ("value", "<f8", (dimension,))])
        end = at + count * record.itemsize
        if end > len(view):
            raise PosesBinaryError(f"cut short at byte {at}: group {group} holds {count} "
                                   f"records of {record.itemsize} bytes")
        parts.setdefault(kind, []).append(np.frombuffer(view[at:end], dtype=record))
        at = end
    if at != len(view):
        raise PosesBinaryError(f"{len(view) - at} bytes after the last group")
    arrays = {}
    for kind, records in parts.items():
        joined = np.concatenate(records)
        joined = joined[np.argsort(joined["key"], kind="stable")]
        arrays[kind] = EstimateArray(
            kind=kind,
            keys=joined["key"].astype(np.int64),
            values=joined["value"].astype(float),
            stamps=np.full(len(joined), np.nan),
            sequence=int(sequence),
            session=session,
            extra_kinds=sorted(k for k in parts if k != kind),
            changed=joined["changed"].astype(np.int64),
        )
    return {"type": "estimate", "sequence": int(sequence), "session": session, "arrays": arrays}


def decode_event(payload: bytes, session: str = "") -> Dict[str, Any]:
    """A sample of ``bin/poses``: a binary estimate (see :func:`decode_poses`) or, starting
    with ``{``, a JSON event (the ``lagged`` marker)."""
    if bytes(payload[:1]) == b"{":
        return json.loads(bytes(payload).decode("utf-8"))
    return decode_poses(payload, session)
