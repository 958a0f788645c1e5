"""Saved estimators (`fit --save` / `export`, posecorr.saved): a file is unpickled only when
its signature under this account's key checks, so a pickle made by anyone else never runs."""
from __future__ import annotations

import os
import pickle
import subprocess
import sys

import numpy as np
import pytest

from posecorr.saved import MAGIC, SavedFileError, SavedFit, load, save


class _Payload:
    """Unpickling this runs `touch MARKER`: what a hostile file would do."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _fitted():
    from posecorr.simulate import simulate_session
    from posecorr.train.pmc import PMC

    table = simulate_session(1, n=60).table
    return SavedFit(PMC("zhou").fit(table.measured, table.reference), table.measured, table.reference)


def _export(saved, out, tmp_path):
    return subprocess.run([sys.executable, "-m", "posecorr.cli", "export", str(saved), "-o", str(out)],
                          capture_output=True, text=True, cwd=tmp_path)


def test_a_foreign_pickle_is_refused_before_it_runs(tmp_path):
    marker = tmp_path / "ran"
    for name, blob in {"plain pickle": pickle.dumps(_Payload(str(marker))),
                       "forged header": MAGIC + b"0" * 64 + b"\n" + pickle.dumps(_Payload(str(marker)))}.items():
        evil = tmp_path / f"{name.replace(' ', '-')}.pkl"
        evil.write_bytes(blob)
        run = _export(evil, tmp_path / "out.onnx", tmp_path)
        assert run.returncode == 2, (name, run.stderr)
        assert "refusing to unpickle" in run.stderr and str(evil) in run.stderr, run.stderr
        assert len(run.stderr.strip().splitlines()) == 1
        assert not marker.exists(), f"{name}: the payload ran"
        assert not (tmp_path / "out.onnx").exists()


def test_save_load_round_trip_and_one_changed_byte_is_refused(tmp_path):
    fit = _fitted()
    path = tmp_path / "est.pkl"
    save(path, fit)
    back = load(path)
    np.testing.assert_array_equal(back.measured, fit.measured)
    np.testing.assert_array_equal(back.estimator.predict(fit.measured[:5]), fit.estimator.predict(fit.measured[:5]))
    blob = bytearray(path.read_bytes())
    blob[-3] ^= 1
    path.write_bytes(bytes(blob))
    with pytest.raises(SavedFileError, match="signature does not match"):
        load(path)


def test_another_accounts_key_is_not_trusted(tmp_path, monkeypatch):
    path = tmp_path / "est.pkl"
    save(path, _fitted())
    monkeypatch.setenv("POSECORR_KEY_FILE", str(tmp_path / "other" / "estimator.key"))
    with pytest.raises(SavedFileError, match="saved no estimator"):
        load(path)
    save(tmp_path / "mine.pkl", _fitted())  # creates the other key
    assert oct(os.stat(tmp_path / "other" / "estimator.key").st_mode & 0o777) == "0o600"
    with pytest.raises(SavedFileError, match="signature does not match"):
        load(path)
