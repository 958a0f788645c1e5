"""The digests a posecorr model carries (docs/design.md, "Integrity"); the model's in the stdlib alone.

Metadata `model_digest` = ``crc32c:`` and eight lowercase hexadecimal digits: the CRC-32C
(Castagnoli) of the file's bytes with those eight digits read as ``00000000``. The value
has a fixed width, so the exporter serialises the model once with the zeros, computes the
CRC and writes the digits over the zeros, and a loader checks a file as it lies, without
serialising anything again (libposecorr: api.c's pc_check_digest).

Metadata `training_data_digest` = ``sha256:`` and the hex digest of the arrays a model was
fitted on (`data_digest`): `apply` tells a table the model was fitted on by it.
"""
from __future__ import annotations

import hashlib
from typing import Any

from .onnx_meta import _Malformed, _varint

__all__ = ["KEY", "PLACEHOLDER", "crc32c", "data_digest", "digest_span", "file_digest", "length_delimited", "sign"]

KEY = "model_digest"
PREFIX = b"crc32c:"
PLACEHOLDER = "crc32c:00000000"
_METADATA_PROPS, _KEY, _VALUE = 14, 1, 2


def _table() -> list[int]:
    out = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        out.append(c)
    return out


_TABLE = _table()


def crc32c(data: bytes, crc: int = 0) -> int:
    """CRC-32C of `data` continuing `crc` (0 to start); crc32c(b"123456789") = 0xE3069283."""
    crc ^= 0xFFFFFFFF
    table = _TABLE
    for byte in data:
        crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def length_delimited(data: bytes, start: int, end: int):
    """(field number, payload start, payload end) of the bytes fields in [start, end)."""
    at = start
    while at < end:
        key, at = _varint(data, at)
        wire = key & 7
        if wire == 0:
            _, at = _varint(data, at)
        elif wire in (1, 5):
            at += 8 if wire == 1 else 4
        elif wire == 2:
            size, at = _varint(data, at)
            if at + size > end:
                raise _Malformed(f"field {key >> 3} runs past the end")
            yield key >> 3, at, at + size
            at += size
        else:
            raise _Malformed(f"unsupported wire type {wire}")


def digest_spans(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of every `model_digest` value in a serialised model."""
    spans = []
    for number, m0, m1 in length_delimited(data, 0, len(data)):
        if number != _METADATA_PROPS:
            continue
        fields = {n: (a, b) for n, a, b in length_delimited(data, m0, m1)}
        key = fields.get(_KEY)
        if key and data[key[0]:key[1]] == KEY.encode():
            spans.append(fields.get(_VALUE, (m1, m1)))  # no value: an empty one, as in C
    return spans


def digest_span(data: bytes) -> tuple[int, int] | None:
    """The one `model_digest` value's (start, end); None without one. Raises ValueError for
    a file holding two."""
    spans = digest_spans(data)
    if len(spans) > 1:
        raise ValueError("metadata model_digest appears twice")
    return spans[0] if spans else None


def file_digest(data: bytes, span: tuple[int, int]) -> str:
    """The digest `data` should carry, its value at `span` (15 bytes) read as the zeros."""
    at = span[0] + len(PREFIX)
    crc = crc32c(data[at + 8:], crc32c(b"00000000", crc32c(data[:at])))
    return f"crc32c:{crc:08x}"


def sign(data: bytes) -> bytes:
    """A serialised model whose `model_digest` holds PLACEHOLDER, with the digits filled in."""
    span = digest_span(data)
    if span is None or data[span[0]:span[1]] != PLACEHOLDER.encode():
        raise ValueError(f"the model's metadata {KEY} must be {PLACEHOLDER!r} before signing")
    return data[:span[0]] + file_digest(data, span).encode() + data[span[1]:]


def data_digest(measured: Any, reference: Any = None, t: Any = None) -> str:
    """`sha256:<hex>` of the training arrays, as float64 little-endian C-order bytes,
    each preceded by its shape, so that a model can be traced to the exact data it saw.
    `t`: the times, for a model that takes them (the same poses at other times are other
    data to it); None leaves the digest of a model without time as it always was."""
    import numpy as np  # the model digest's functions are stdlib only

    h = hashlib.sha256()
    arrays = [("measured", measured), ("reference", reference)] + ([("t", t)] if t is not None else [])
    for name, arr in arrays:
        if arr is None:
            h.update(f"{name}:none;".encode())
            continue
        a = np.ascontiguousarray(np.asarray(arr, dtype="<f8"))
        h.update(f"{name}:{a.shape};".encode())
        h.update(a.tobytes())
    return "sha256:" + h.hexdigest()


# What a model's metadata says of the poses it was fitted on: its training arrays, and for a
# fit with a test split the whole table the fit split.
FITTED_DIGESTS = {"training": "training_data_digest", "table": "fitted_table_digest"}


def fitted_on(measured: Any, reference: Any, metadata: Any, t: Any = None) -> str | bool | None:
    """"training" where (measured, reference) are the arrays the model was fitted on, "table"
    where they are the table a fit with a test split read, False where neither, None where
    the model's metadata (a dict of decoded values) states no digest. `t`: the table's times,
    where it has them: a model that takes time states the digest with them, one that does
    not, without."""
    expected = {kind: metadata.get(key) for kind, key in FITTED_DIGESTS.items() if metadata.get(key)}
    if not expected:
        return None
    digests = {data_digest(measured, reference)} | ({data_digest(measured, reference, t)} if t is not None else set())
    return next((kind for kind, value in expected.items() if value in digests), False)
