"""The digests a posecorr model carries (docs/design.md, "Integrity"); the model's in the stdlib alone.

Metadata `model_digest` = ``crc32c:`` and eight lowercase hexadecimal digits: the CRC-32C
(Castagnoli) of the file's bytes with those eight digits read as ``00000000``. The value
has a fixed width, so the exporter serialises the model once with the zeros, computes the
CRC and writes the digits over the zeros, and a loader checks a file as it lies, without
serialising anything again (libposecorr: api.c's pc_check_digest).

Metadata `training_data_digest` = ``sha256:`` and the hex digest of the arrays a model was
fitted on (`data_digest`): `apply` tells a table the model was fitted on by it.
`training_set_digest` = the same poses' digest whatever their order (`set_digest`): a table of
them sorted, or reversed, is still the fit's poses.
"""
from __future__ import annotations

import hashlib
from typing import Any

from .onnx_meta import _Malformed, _varint

__all__ = ["KEY", "PLACEHOLDER", "crc32c", "data_digest", "digest_span", "file_digest", "length_delimited",
           "row_order", "set_digest", "sign"]

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


def _named_arrays(measured: Any, reference: Any, t: Any) -> list[tuple[str, Any]]:
    """(name, float64 little-endian C-order array or None) of the arrays a digest reads; `t`
    only where given."""
    import numpy as np  # the model digest's functions are stdlib only

    arrays = [("measured", measured), ("reference", reference)] + ([("t", t)] if t is not None else [])
    return [(name, None if a is None else np.ascontiguousarray(np.asarray(a, dtype="<f8"))) for name, a in arrays]


def _layout(named: list[tuple[str, Any]]) -> bytes:
    return "".join(f"{name}:none;" if a is None else f"{name}:{a.shape};" for name, a in named).encode()


def data_digest(measured: Any, reference: Any = None, t: Any = None) -> str:
    """`sha256:<hex>` of the training arrays, as float64 little-endian C-order bytes,
    each preceded by its shape, so that a model can be traced to the exact data it saw.
    `t`: the times, for a model that takes them (the same poses at other times are other
    data to it); None leaves the digest of a model without time as it always was."""
    h = hashlib.sha256()
    for name, a in _named_arrays(measured, reference, t):
        h.update(_layout([(name, a)]))
        if a is not None:
            h.update(a.tobytes())
    return "sha256:" + h.hexdigest()


def _row_digests(named: list[tuple[str, Any]]) -> list[bytes]:
    """SHA-256 of each row's values (its measured, reference and t, as `data_digest` reads them)."""
    import numpy as np

    columns = [a.reshape(len(a), int(np.prod(a.shape[1:]))) for _, a in named if a is not None]
    rows = np.ascontiguousarray(np.concatenate(columns, axis=1))
    return [hashlib.sha256(row).digest() for row in rows]


def _sorted_rows(named: list[tuple[str, Any]]) -> tuple[list[int], list[bytes]]:
    digests = _row_digests(named)
    # stable: identical rows keep their order, so an order is a function of the rows alone
    order = sorted(range(len(digests)), key=digests.__getitem__)
    return order, [digests[i] for i in order]


def row_order(measured: Any, reference: Any = None, t: Any = None) -> list[int]:
    """The rows sorted by their SHA-256, the order `set_digest` reads them in: two tables of the
    same rows in other orders list them alike (identical rows are interchangeable)."""
    return _sorted_rows(_named_arrays(measured, reference, t))[0]


def set_digest(measured: Any, reference: Any = None, t: Any = None) -> str:
    """`sha256:<hex>` of the arrays' shapes and their rows' SHA-256s in `row_order`: the digest
    of the same poses in any order (each row's measured, reference and `t` as `data_digest`
    reads them; a row twice is twice in it)."""
    named = _named_arrays(measured, reference, t)
    h = hashlib.sha256(_layout(named))
    for row in _sorted_rows(named)[1]:
        h.update(row)
    return "sha256:" + h.hexdigest()


# What a model's metadata says of the poses it was fitted on: its training arrays, and for a
# fit with a test split the whole table the fit split; by `data_digest`, and the same poses in
# any order by `set_digest` (models written before that state no such key).
FITTED_DIGESTS = {"training": "training_data_digest", "table": "fitted_table_digest"}
FITTED_SET_DIGESTS = {"training": "training_set_digest", "table": "fitted_table_set_digest"}
# `fitted_on`'s word for the poses of a kind in another order: "training-reordered"
REORDERED = "-reordered"


def _matched(keys: dict[str, str], digest: Any, measured: Any, reference: Any, metadata: Any,
             t: Any) -> str | bool | None:
    """The kind whose digest `metadata` states (under `keys`) is `digest`'s of the arrays, with
    or without `t`; False where none is; None where it states none."""
    expected = {kind: metadata.get(key) for kind, key in keys.items() if metadata.get(key)}
    if not expected:
        return None
    digests = {digest(measured, reference)} | ({digest(measured, reference, t)} if t is not None else set())
    return next((kind for kind, value in expected.items() if value in digests), False)


def fitted_on(measured: Any, reference: Any, metadata: Any, t: Any = None) -> str | bool | None:
    """"training" where (measured, reference) are the arrays the model was fitted on, "table"
    where they are the table a fit with a test split read, either with REORDERED where they are
    those poses in another order, False where neither, None where the model's metadata (a
    dict of decoded values) states no digest. `t`: the table's times, where it has them: a
    model that takes time states the digest with them, one that does not, without."""
    exact = _matched(FITTED_DIGESTS, data_digest, measured, reference, metadata, t)
    if exact:
        return exact
    # only where the order-bound digests failed: a row's digest each costs more than one pass
    unordered = _matched(FITTED_SET_DIGESTS, set_digest, measured, reference, metadata, t)
    if unordered:
        return unordered + REORDERED
    return None if exact is None and unordered is None else False
