"""Fitted estimators on disk (`posecorr fit --save`, read by `posecorr export`).

A fitted estimator is a torch/scikit-learn object graph; pickle is the one format that keeps
all of it, and unpickling runs whatever code the file names. So a saved file carries an
HMAC-SHA256 of its bytes under a key that only this user's account holds, and a file is
unpickled only after its signature checks: a file written by anyone else (or changed by one
byte) is refused before a single byte of it is unpickled. What is trusted: files saved by
`posecorr fit --save` under this account (the key file, created on the first save with mode
0600). To export on another machine, copy the key file there, or fit there.

Key file: $POSECORR_KEY_FILE, else $XDG_CONFIG_HOME/posecorr/estimator.key (default
~/.config/posecorr/estimator.key).
"""
from __future__ import annotations

import hashlib
import hmac
import os
import pickle
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

MAGIC = b"posecorr-estimator 1\n"
SIGNATURE_HEX = 64
# A saved estimator is a few MB at most (the paper's largest MLP, its training arrays): a
# larger file is refused before it is read whole.
MAX_BYTES = 256 << 20


class SavedFileError(ValueError):
    """A file that is not a saved estimator this account may load."""


@dataclass
class SavedFit:
    """A fitted estimator with the training arrays its export checks parity on, and what
    the fit scored it on: its held-out poses (a test split's: the graph scores them again)
    and the figures the file states (`test_metrics`). A file saved before these were kept
    reads them as None: its export states no figures."""

    estimator: Any
    measured: np.ndarray
    reference: np.ndarray
    t: np.ndarray | None = None
    heldout: tuple | None = None
    test_metrics: dict[str, Any] | None = None
    # The digests of the whole table a fit with a test split read (its training rows are a
    # part), in its order and in any: `apply` on that table says whose poses they are.
    table_digest: str | None = None
    table_set_digest: str | None = None

    def export_arguments(self) -> dict[str, Any]:
        """`to_onnx`'s keyword arguments for the file the fit wrote."""
        stated = {} if self.test_metrics is None else {"test_metrics": self.test_metrics}
        table = {key: value for key, value in (("fitted_table_digest", self.table_digest),
                                               ("fitted_table_set_digest", self.table_set_digest)) if value is not None}
        return {"measured": self.measured, "reference": self.reference, "t": self.t, "heldout": self.heldout,
                **stated, **table}


def key_path() -> Path:
    explicit = os.environ.get("POSECORR_KEY_FILE")
    if explicit:
        return Path(explicit)
    config = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config")
    return config / "posecorr" / "estimator.key"


def _key(create: bool) -> bytes:
    path = key_path()
    if create and not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            pass  # another process created it first: read theirs
        else:
            with os.fdopen(fd, "w") as handle:
                handle.write(secrets.token_hex(32) + "\n")
    try:
        text = path.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        raise SavedFileError(f"no key file {path}: this account has saved no estimator, so it trusts none; "
                             "refusing to unpickle (see posecorr.saved)") from None
    if len(text) != 64 or any(c not in "0123456789abcdef" for c in text):
        raise SavedFileError(f"{path}: not a posecorr key file (64 hexadecimal digits expected)")
    return bytes.fromhex(text)


def _signature(key: bytes, payload: bytes) -> bytes:
    return hmac.new(key, payload, hashlib.sha256).hexdigest().encode("ascii")


def save(path: str | Path, fit: SavedFit, write: Callable[[Path, bytes], None] | None = None) -> None:
    """Writes fit signed under this account's key (created when missing); `write` as in
    `export.to_onnx` (default: atomically, `safeio.write_bytes`)."""
    if write is None:
        from .safeio import write_bytes as write
    payload = pickle.dumps({"estimator": fit.estimator, "measured": np.asarray(fit.measured),
                            "reference": np.asarray(fit.reference),
                            "t": None if fit.t is None else np.asarray(fit.t),
                            "heldout": fit.heldout, "test_metrics": fit.test_metrics,
                            "table_digest": fit.table_digest, "table_set_digest": fit.table_set_digest})
    write(Path(path), MAGIC + _signature(_key(create=True), payload) + b"\n" + payload)


def load(path: str | Path) -> SavedFit:
    """Reads a file `save` wrote under this account; refuses anything else unread."""
    path = Path(path)
    with open(path, "rb") as handle:
        head = handle.read(len(MAGIC) + SIGNATURE_HEX + 1)
        if not head.startswith(MAGIC) or len(head) < len(MAGIC) + SIGNATURE_HEX + 1 or head[-1:] != b"\n":
            raise SavedFileError(f"{path}: not an estimator saved by `posecorr fit --save` (no posecorr header); "
                                 "refusing to unpickle it: a pickle runs code when it is loaded")
        payload = handle.read(MAX_BYTES + 1)
    if len(payload) > MAX_BYTES:
        raise SavedFileError(f"{path}: larger than {MAX_BYTES >> 20} MiB: not a saved estimator")
    signature = head[len(MAGIC):-1]
    if not hmac.compare_digest(signature, _signature(_key(create=False), payload)):
        raise SavedFileError(f"{path}: its signature does not match this account's key ({key_path()}): it was "
                             "not saved here or was changed since; refusing to unpickle it")
    data = pickle.loads(payload)
    if not (isinstance(data, dict) and hasattr(data.get("estimator"), "forward")):
        raise SavedFileError(f"{path}: not a posecorr estimator (no forward method)")
    return SavedFit(data["estimator"], data["measured"], data["reference"], data.get("t"), data.get("heldout"),
                    data.get("test_metrics"), data.get("table_digest"), data.get("table_set_digest"))
