"""Hardening (issue 14): every failure one clear line, nothing lost, nothing absurd accepted.

* a corpus of bad tables, bad models and bad output paths through every verb: exit 2,
  one line naming the file (row and column where there is one), never a traceback;
* strict numbers, BOM, degenerate data, exceptions crossing the sweep's process pool;
* safe writes: atomic replacement, outputs equal to inputs refused, torn appends repaired;
* `apply` on measurement-only tables, streamed in chunks, metrics equal to the in-memory ones.
"""
from __future__ import annotations

import json
import os
import pickle
import shlex
import stat
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr.cli import main
from posecorr.controller.runtime import Corrector, PoseCorrError
from posecorr.data import MEAS_POS, MEAS_QUAT, PoseTable, TableError, read_table, require_rows, write_table
from posecorr.metrics import pose_metrics

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "pmc-zhou.onnx"
HEADER = "meas_x,meas_y,meas_z,meas_qw,meas_qx,meas_qy,meas_qz,ref_x,ref_y,ref_z"
HEADER_Q = HEADER + ",ref_qw,ref_qx,ref_qy,ref_qz"


def _table(n: int = 40, seed: int = 0) -> PoseTable:
    """Experiment III-like poses with a small rigid offset between measured and reference."""
    rng = np.random.default_rng(seed)
    p = np.array([0.0, -0.6, 0.5]) + rng.uniform(-0.1, 0.1, (n, 3))
    R = Rotation.from_euler("xyz", rng.uniform(-0.5, 0.5, (n, 3)))
    q = R.as_quat(scalar_first=True)
    meas_p = p + np.array([0.004, -0.002, 0.003]) + rng.normal(scale=3e-4, size=(n, 3))
    return PoseTable(meas_p, q, p, q, {"id": np.arange(n).astype(str).astype(object)})


def _lines(n: int = 12) -> list[str]:
    t = _table(n)
    return [",".join(repr(float(v)) for v in row) for row in np.concatenate([t.measured, t.reference], axis=1)]


def _run(argv: list[str], capsys) -> tuple[int | None, str, str | None]:
    """main(argv) in this process: (exit code, stderr, the exception that escaped or None)."""
    capsys.readouterr()
    try:
        code = main(argv)
        escaped = None
    except SystemExit as exc:  # argparse usage errors
        code, escaped = exc.code, None
    except BaseException as exc:  # noqa: BLE001 - a traceback is what the corpus hunts for
        code, escaped = None, f"{type(exc).__name__}: {exc}"
    return code, capsys.readouterr().err, escaped


# --- the bad-input corpus -----------------------------------------------------------------

def _bad_tables(folder: Path) -> list[tuple[str, Path, list[str], bool]]:
    """(name, path, substrings the one line must hold, degenerate-only): degenerate tables
    are fine for `apply` (one pose can be corrected) but refused by every verb that fits."""
    good = _lines(12)
    rows = "\n".join(good)
    cases: list[tuple[str, str | bytes, list[str], bool]] = [
        ("missing column", HEADER_Q.replace("meas_qz,", "") + "\n", ["row 1", "column meas_qz"], False),
        ("not a number", f"{HEADER_Q}\n{good[0]}\n" + good[1].replace(good[1].split(",")[1], "abc", 1),
         ["row 3", "column meas_y", "expected a number"], False),
        ("underscore", f"{HEADER_Q}\n{good[0]}\n1_0" + good[1][good[1].index(","):],
         ["row 3", "column meas_x", "plain decimal"], False),
        # `sed 's/$/,x/'` on a file with Windows line endings: the csv module's own words
        # ("do you need to open the file in universal-newline mode?") left the user nowhere
        ("mixed line endings", f"{HEADER_Q}\r\n{good[0]}\r,x\n{good[1]}\r\n",
         ["row 2", "carriage return", "line endings are mixed"], False),
        ("infinity", f"{HEADER_Q}\ninfinity" + good[0][good[0].index(","):], ["row 2", "column meas_x", "finite"],
         False),
        ("hex", f"{HEADER_Q}\n0x1p3" + good[0][good[0].index(","):], ["row 2", "column meas_x", "number"], False),
        ("nan", f"{HEADER_Q}\n{good[0]}\nnan" + good[1][good[1].index(","):], ["row 3", "column meas_x", "finite"],
         False),
        ("overflow", f"{HEADER_Q}\n1e999" + good[0][good[0].index(","):], ["row 2", "column meas_x", "finite"],
         False),
        ("1e30 m", f"{HEADER_Q}\n1e30" + good[0][good[0].index(","):], ["row 2", "column meas_x", "from the origin"],
         False),
        ("empty cell", f"{HEADER_Q}\n," + good[0].split(",", 1)[1], ["row 2", "column meas_x", "empty"], False),
        ("zero quaternion", f"{HEADER_Q}\n0.1,0.2,0.3,0,0,0,0,0.1,0.2,0.3,1,0,0,0\n",
         ["row 2", "column meas_qw..meas_qz", "zero quaternion"], False),
        ("non-unit quaternion", f"{HEADER_Q}\n0.1,0.2,0.3,0.9,0,0,0,0.1,0.2,0.3,1,0,0,0\n",
         ["row 2", "column meas_qw..meas_qz", "norm"], False),
        ("zero reference quaternion", f"{HEADER_Q}\n0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,0,0,0,0\n",
         ["row 2", "column ref_qw..ref_qz"], False),
        ("field count", f"{HEADER_Q}\n{good[0]}\n0.1,0.2\n", ["row 3", "2 fields"], False),
        ("not UTF-8", f"{HEADER_Q}\n{good[0]}\n".encode() + b"0.1,\xff\xfe" + good[1].encode()[5:] + b"\n",
         ["row 3", "UTF-8"], False),
        ("duplicate column", HEADER_Q.replace("ref_x", "meas_x") + "\n" + good[0] + "\n",
         ["row 1", "column meas_x", "duplicate"], False),
        ("partial ref_q", HEADER + ",ref_qw\n" + good[0].rsplit(",", 3)[0] + "\n", ["row 1", "column ref_qx"],
         False),
        ("empty file", "", ["empty file"], False),
        ("header only", HEADER_Q + "\n", ["no data rows"], False),
        ("control characters", f"{HEADER_Q}\n\x1b[31m" + good[0][good[0].index(","):],
         ["row 2", "column meas_x", "\\x1b"], False),
        ("one row", f"{HEADER_Q}\n{good[0]}\n", ["1 row,"], True),
        # two: the report's rigid baseline takes three (and then writes its page without a diagnosis)
        ("two rows", f"{HEADER_Q}\n" + "\n".join(good[:2]) + "\n", ["2 rows"], True),
        ("400 identical poses", f"{HEADER_Q}\n" + f"{good[0]}\n" * 400, ["only 1 distinct"], True),
        ("1e-15 spread", None, ["span only"], True),
    ]
    out = []
    for i, (name, body, where, degenerate) in enumerate(cases):
        path = folder / f"bad{i:02d}.csv"
        if body is None:  # identical poses up to 1e-15 m of noise
            t = _table(40)
            t = PoseTable(t.meas_p[:1] + np.random.default_rng(1).normal(scale=1e-15, size=(40, 3)),
                          np.repeat(t.meas_q[:1], 40, 0), np.repeat(t.ref_p[:1], 40, 0), np.repeat(t.ref_q[:1], 40, 0))
            write_table(t, path)
        elif isinstance(body, bytes):
            path.write_bytes(body)
        else:
            path.write_text(body)
        out.append((name, path, where, degenerate))
    out.append(("a folder", folder / "folder.csv", ["is a folder"], False))
    (folder / "folder.csv").mkdir()
    out.append(("missing file", folder / "missing.csv", ["cannot open"], False))
    assert rows
    return out


def _bad_models(folder: Path) -> list[tuple[str, Path]]:
    import onnx
    from onnx import TensorProto, helper

    data = MODEL.read_bytes()
    cases = {"empty": b"", "random bytes": np.random.default_rng(0).bytes(4096),
             "truncated": data[: len(data) // 2], "text": b"meas_x,meas_y\n1,2\n"}
    out = []
    for name, blob in cases.items():
        path = folder / f"{name.replace(' ', '_')}.onnx"
        path.write_bytes(blob)
        out.append((name, path))
    other = helper.make_model(helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])], "other",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 3])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 3])]),
        opset_imports=[helper.make_opsetid("", 17)])
    onnx.save(other, folder / "not_a_corrector.onnx")
    out.append(("not a corrector", folder / "not_a_corrector.onnx"))
    (folder / "dir.onnx").mkdir()
    out.append(("a folder", folder / "dir.onnx"))
    out.append(("missing", folder / "missing.onnx"))
    return out


def _unwritable_folder(folder: Path) -> Path:
    """A folder this user cannot create files in (root ignores permission bits: /sys)."""
    if os.geteuid() == 0:
        return Path("/sys")
    ro = folder / "read-only"
    ro.mkdir()
    ro.chmod(0o555)
    return ro


def test_bad_input_corpus_every_verb(tmp_path, capsys, summary) -> None:
    tables = tmp_path / "tables"
    models = tmp_path / "models"
    paths = tmp_path / "paths"
    for d in (tables, models, paths):
        d.mkdir()
    good_csv = tmp_path / "good.csv"
    write_table(_table(40), good_csv)
    out = tmp_path / "out"
    out.mkdir()

    runs: list[tuple[str, str, list[str], list[str]]] = []   # (verb, case, argv, must contain)
    for name, path, where, degenerate in _bad_tables(tables):
        verbs = {
            "fit": ["fit", str(path), "-o", str(out / "m.onnx"), "--method", "pmc"],
            "diagnose": ["diagnose", str(path)],
            "sweep": ["sweep", str(path), "--repeats", "1", "--no-mlp", "--store", str(out / "s.jsonl"),
                      "--json"],
            "report": ["report", str(path), "--model", str(MODEL), "-o", str(out / "r.html")],
        }
        if not degenerate:
            verbs["apply"] = ["apply", str(MODEL), str(path), "-o", str(out / "a.csv")]
        for verb, argv in verbs.items():
            runs.append((verb, f"table: {name}", argv, [str(path), *where]))
    for name, path in _bad_models(models):
        # Any valid ONNX file has metadata to show: `info` is no failure for those.
        for verb, argv in {
            "apply": ["apply", str(path), str(good_csv), "-o", str(out / "a.csv")],
            "apply --backend onnxruntime": ["apply", str(path), str(good_csv), "-o", str(out / "a.csv"),
                                            "--backend", "onnxruntime"],
            "info": ["info", str(path)],
            "bench": ["bench", str(path), "--n", "50", "--batch", "10"],
            "diagnose --model": ["diagnose", str(good_csv), "--model", str(path)],
            "report --model": ["report", str(good_csv), "--model", str(path), "-o", str(out / "r.html")],
        }.items():
            if not (verb == "info" and name == "not a corrector"):
                runs.append((verb, f"model: {name}", argv, [str(path)]))
    ro = _unwritable_folder(paths)
    folder_out = paths / "a-folder"
    folder_out.mkdir()
    from posecorr.train.pmc import PMC

    t = _table(100)
    from posecorr.saved import SavedFit, save

    estimator = paths / "est.pkl"
    save(estimator, SavedFit(PMC("zhou").fit(t.measured, t.reference), t.measured, t.reference))
    for name, blob in (("not a pickle", b"not a pickle"), ("empty", b"")):
        bad = paths / f"{name.replace(' ', '-')}.pkl"
        bad.write_bytes(blob)
        runs.append(("export", f"estimator: {name}", ["export", str(bad), "-o", str(out / "e.onnx")], [str(bad)]))
    for verb, make in {
        "simulate": lambda o: ["simulate", "--experiment", "1", "-o", str(o)],
        "fit": lambda o: ["fit", str(good_csv), "-o", str(o), "--method", "pmc"],
        "apply": lambda o: ["apply", str(MODEL), str(good_csv), "-o", str(o)],
        "report": lambda o: ["report", str(good_csv), "--model", str(MODEL), "-o", str(o), "--no-diagnosis"],
        "export": lambda o: ["export", str(estimator), "-o", str(o)],
        "sweep": lambda o: ["sweep", str(good_csv), "--repeats", "1", "--no-mlp", "--store", str(o)],
    }.items():
        for name, target, expect in [("output is a folder", folder_out, "is a folder"),
                                     ("folder missing", paths / "no" / "x.out", "does not exist"),
                                     ("unwritable folder", ro / "x.out", str(ro))]:
            runs.append((verb, f"path: {name}", make(target), [str(target) if name != "unwritable folder"
                                                               else str(ro), expect]))
    same = {"fit": ["fit", str(good_csv), "-o", str(good_csv)],
            "apply": ["apply", str(MODEL), str(good_csv), "-o", str(MODEL)],
            "apply ": ["apply", str(MODEL), str(good_csv), "-o", str(good_csv)],
            "report": ["report", str(good_csv), "--model", str(MODEL), "-o", str(good_csv)],
            "sweep": ["sweep", str(good_csv), "--store", str(good_csv)]}
    for verb, argv in same.items():
        runs.append((verb.strip(), "path: output is an input", argv, ["is also an input"]))

    before = {p: p.read_bytes() for p in (good_csv, MODEL)}
    failures, tracebacks = [], 0
    for verb, case, argv, expected in runs:
        code, err, escaped = _run(argv, capsys)
        lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith(("  ", "sweep:"))]
        if escaped or "Traceback" in err:
            tracebacks += 1
        ok = (escaped is None and code == 2 and len(lines) == 1 and "Traceback" not in err
              and all(e in lines[0] for e in expected))
        if not ok:
            failures.append(f"{verb} / {case}: exit {code}, escaped {escaped}, stderr {err.strip()[-300:]!r}, "
                            f"expected {expected}")
    verbs = sorted({v.split()[0] for v, *_ in runs})
    summary(f"bad-input corpus: {len(runs)} cases over {len(verbs)} verbs ({', '.join(verbs)}): "
            f"{len(runs) - len(failures)} ended in one located line with exit 2, {tracebacks} tracebacks")
    assert not failures, "\n".join(failures)
    assert tracebacks == 0
    assert {p: p.read_bytes() for p in (good_csv, MODEL)} == before  # inputs untouched


# --- strict numbers and degenerate data ------------------------------------------------------

def test_float_forms_beyond_plain_decimal_are_refused(tmp_path) -> None:
    row = "0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3"
    for text in ("1_0", "infinity", "-inf", "NaN", "0x10", "1e400", "١٢", " 1 2"):
        path = tmp_path / "t.csv"
        path.write_text(f"{HEADER}\n{row}\n{text}{row[3:]}\n")
        with pytest.raises(TableError, match=r"row 3, column meas_x"):
            read_table(path)
    path.write_text(f"{HEADER}\n{row}\n+.5e-1,2.,-3E+0,1.0,0,0,0,1,2,3\n")
    assert read_table(path).meas_p[1].tolist() == [0.05, 2.0, -3.0]


def test_a_byte_order_mark_is_skipped(tmp_path) -> None:
    path = tmp_path / "bom.csv"
    t = _table(12)
    write_table(t, path)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    back = read_table(path)
    assert list(back.extras["id"]) == list(t.extras["id"])  # "id", not "\ufeffid"
    np.testing.assert_array_equal(back.measured, t.measured)


def test_degenerate_tables_are_refused_with_the_reason() -> None:
    t = _table(40)
    same = t.subset(np.zeros(40, dtype=int))
    with pytest.raises(TableError, match="40 rows but only 1 distinct measured pose;"):
        require_rows(same, 10, "a fit")
    jitter = PoseTable(same.meas_p + 1e-15 * np.arange(40)[:, None], same.meas_q, same.ref_p, same.ref_q)
    with pytest.raises(TableError, match=r"measured positions span only 3.9e-14 m"):
        require_rows(jitter, 10, "a fit")
    require_rows(t, 10, "a fit")  # a real spread passes


def test_errors_cross_process_pools_intact(tmp_path) -> None:
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from posecorr.train.protocol import run_sweep
    from posecorr.train.spec import ModelSpec

    err = TableError("d.csv", "expected a number, got 'x'", 7, "meas_y")
    back = pickle.loads(pickle.dumps(err))
    assert (type(back), str(back), back.row, back.column) == (TableError, str(err), 7, "meas_y")
    perr = pickle.loads(pickle.dumps(PoseCorrError("m.onnx: bad", 3)))
    assert (str(perr), perr.status) == ("m.onnx: bad", 3)
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("forkserver")) as pool:
        with pytest.raises(TableError) as info:
            pool.submit(_raise_table_error).result()
    assert str(info.value) == "w.csv, row 4, column ref_z: expected a finite number, got 'nan'"
    # In a sweep, a run that fails in a worker ends the sweep with its own error, not a
    # BrokenProcessPool, and the runs that finished are in the store.
    table = _table(100)
    store = tmp_path / "s.jsonl"
    failing = ModelSpec("pmc", "zhou", options={"degree": 3})  # passes the grid's checks, fails in its run
    with pytest.raises(ValueError, match="degree must be 1 \\(affine\\) or 2 \\(quadratic\\), got 3"):
        run_sweep(table, [ModelSpec("pmc", "zhou"), failing], repeats=3, store=store, workers=2, progress=False)
    stored = [json.loads(line) for line in store.read_text().splitlines()]
    assert stored and all(row["key"] == "zhou-pmc" for row in stored)


def _raise_table_error() -> None:
    raise TableError("w.csv", "expected a finite number, got 'nan'", 4, "ref_z")


# --- safe writes ------------------------------------------------------------------------------

def test_atomic_output_replaces_whole_or_not_at_all(tmp_path) -> None:
    from posecorr.safeio import atomic_output, write_bytes

    target = tmp_path / "model.onnx"
    write_bytes(target, b"old model")
    with pytest.raises(RuntimeError):
        with atomic_output(target, "wb") as handle:
            handle.write(b"half of a new")
            raise RuntimeError("disk full")
    assert target.read_bytes() == b"old model"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx"]  # no temporary left
    inode = target.stat().st_ino
    write_bytes(target, b"new model")
    assert target.read_bytes() == b"new model" and target.stat().st_ino != inode  # renamed over, not rewritten


@pytest.mark.parametrize("without", ["O_TMPFILE", "/proc"])
def test_fallback_writes_keep_the_permissions_open_gives(tmp_path, monkeypatch, without) -> None:
    """Where the file system has no unnamed files (or /proc is missing to name one), the new
    file is a named temporary: it must still end with the mode a plain open() gives under the
    umask, not the 0o600 of a private temporary, and leave no temporary behind."""
    from posecorr import safeio

    if without == "O_TMPFILE":
        monkeypatch.setattr(safeio, "_unnamed_file", lambda folder: None)
    else:
        def no_proc(*args, **kwargs):
            raise FileNotFoundError(2, "No such file or directory", args[0])
        monkeypatch.setattr(safeio.os, "link", no_proc)
    old = os.umask(0o027)
    try:
        (tmp_path / "plain").write_bytes(b"")  # the kernel's own creation mode: the truth
        safeio.write_bytes(tmp_path / "model.onnx", b"old")
        safeio.write_bytes(tmp_path / "model.onnx", b"new model")
    finally:
        os.umask(old)
    mode = stat.S_IMODE((tmp_path / "plain").stat().st_mode)
    assert mode == 0o640
    assert stat.S_IMODE((tmp_path / "model.onnx").stat().st_mode) == mode
    assert (tmp_path / "model.onnx").read_bytes() == b"new model"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.onnx", "plain"]


def test_torn_last_line_is_moved_aside_and_the_next_record_kept(tmp_path, capsys) -> None:
    from posecorr.analysis.ledger import append_entry, ledger_path, read_ledger

    data = tmp_path / "d.csv"
    append_entry(data, {"model": "a.onnx"})
    path = ledger_path(data)
    with open(path, "ab") as handle:
        handle.write(b'{"model": "b.onn')  # killed mid-append
    assert [r["model"] for r in read_ledger(data)] == ["a.onnx"]  # reading skips it, and says so
    assert "line 2" in capsys.readouterr().err
    append_entry(data, {"model": "c.onnx"})
    assert "moved to" in capsys.readouterr().err
    assert [r["model"] for r in read_ledger(data)] == ["a.onnx", "c.onnx"]
    assert path.with_name(path.name + ".corrupt").read_text() == '{"model": "b.onn\n'


def test_a_sweep_store_with_a_torn_line_resumes_with_every_run(tmp_path) -> None:
    from posecorr.train.protocol import run_sweep
    from posecorr.train.spec import ModelSpec

    table = _table(100)
    store = tmp_path / "s.jsonl"
    configs = [ModelSpec("pmc", "zhou"), ModelSpec("pmc", "quat")]
    run_sweep(table, configs, repeats=2, store=store, workers=1, progress=False)
    text = store.read_text()
    store.write_text(text + text.splitlines()[0][:30])  # a torn third record
    result = run_sweep(table, configs, repeats=3, store=store, workers=1, progress=False)
    assert len(result.rows) == 6
    lines = store.read_text().splitlines()
    assert len(lines) == 6 and all(json.loads(line) for line in lines)
    assert (tmp_path / "s.jsonl.corrupt").exists()


# --- apply: streaming, measurement-only tables -------------------------------------------------

def test_apply_on_a_measurement_only_table(tmp_path, capsys) -> None:
    t = _table(50)
    full = tmp_path / "full.csv"
    write_table(t, full)
    meas_only = tmp_path / "meas_only.csv"
    with open(full) as src, open(meas_only, "w") as dst:  # drop the ref_* columns
        for line in src:
            cells = line.rstrip("\n").split(",")
            dst.write(",".join(cells[:8]) + "\n")
    code, err, escaped = _run(["apply", str(MODEL), str(meas_only), "-o", str(tmp_path / "out.csv"), "--json"],
                              capsys)
    assert code == 0 and escaped is None, err
    out = read_csv_columns(tmp_path / "out.csv")
    expected = Corrector(MODEL).correct(t.measured)
    corr = np.stack([out[c] for c in ("corr_x", "corr_y", "corr_z", "corr_qw", "corr_qx", "corr_qy", "corr_qz")], 1)
    np.testing.assert_allclose(corr, expected, rtol=0, atol=1e-8)  # nine digits of float32 values
    for i, c in enumerate(MEAS_POS + MEAS_QUAT):
        np.testing.assert_array_equal(out[c], t.measured[:, i])  # the raw poses beside, exact
    assert not any(c.startswith("ref_") for c in out)
    # The same table with references: the metrics are those of the corrected columns.
    capsys.readouterr()
    assert main(["apply", str(MODEL), str(full), "-o", str(tmp_path / "out2.csv"), "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    want = pose_metrics(t.reference, expected)
    for key, value in want.items():
        assert payload["corrected"][key] == pytest.approx(value, rel=1e-9)
    assert payload["raw"] == pytest.approx(pose_metrics(t.reference, t.measured), rel=1e-12)


def test_apply_streams_in_chunks_with_the_same_result(tmp_path) -> None:
    from posecorr.controller.apply import apply_file

    t = _table(1000, seed=4)
    path = tmp_path / "t.csv"
    write_table(t, path)
    whole = apply_file(MODEL, path, tmp_path / "a.csv", chunk_rows=1_000_000)
    chunked = apply_file(MODEL, path, tmp_path / "b.csv", chunk_rows=7)
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        assert chunked["corrected"][key] == pytest.approx(whole["corrected"][key], rel=1e-12)
    # An error in a late chunk names its row and leaves no output behind.
    lines = path.read_text().splitlines()
    lines[900] = lines[900].replace(",", ",x", 1)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(TableError, match="row 901, column meas_x"):
        apply_file(MODEL, path, tmp_path / "c.csv", chunk_rows=7)
    assert not (tmp_path / "c.csv").exists()


def _bounded_model(tmp_path: Path) -> Path:
    """A PMC fitted on 200 poses of `_table`, exported with its box (input_bounds)."""
    from posecorr.train.pmc import PMC

    t = _table(200, seed=5)
    model = tmp_path / "bounded.onnx"
    PMC(representation="zhou").fit(t.measured, t.reference).to_onnx(model, measured=t.measured,
                                                                       reference=t.reference)
    return model


def test_apply_names_the_row_a_model_refuses_in_a_late_chunk(tmp_path, capsys) -> None:
    """A pose outside the box a model was fitted on (input_bounds) is refused by the runtime,
    which counts poses within its call: apply names the file's row and column (not the
    chunk's pose number), ends in one line with exit 2 and writes nothing; so do report and
    diagnose --model."""
    from posecorr.controller.apply import apply_file

    model = _bounded_model(tmp_path)
    path = tmp_path / "t.csv"
    write_table(_table(60, seed=6), path)
    lines = path.read_text().splitlines()
    cells = lines[45].split(",")
    cells[2] = "5.0"  # meas_y of row 46, 5 m away: inside the table's 1000 m, outside the box
    lines[45] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    assert lines[0].split(",")[2] == "meas_y"
    with pytest.raises(TableError, match=r"row 46, column meas_y: .*outside the range the model was fitted on"):
        apply_file(model, path, tmp_path / "out.csv", chunk_rows=7)
    assert not (tmp_path / "out.csv").exists()
    code, err, escaped = _run(["apply", str(model), str(path), "-o", str(tmp_path / "out.csv")], capsys)
    assert code == 2 and escaped is None and len(err.strip().splitlines()) == 1
    assert "row 46, column meas_y" in err and not (tmp_path / "out.csv").exists()
    assert "in column" not in err     # the table's column named once, not the model's input index too
    # report and diagnose fit: 5 m off is a gross outlier there, refused as such; 0.3 m off
    # is named as a suspect (a warning) and refused by the model
    code, err, escaped = _run(["report", str(path), "--model", str(model), "-o", str(tmp_path / "r.html")], capsys)
    assert code == 2 and escaped is None and len(err.strip().splitlines()) == 1
    assert "t.csv, row 46: gross outlier(s)" in err and not (tmp_path / "r.html").exists()
    cells[2] = "-0.3"
    lines[45] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    code, err, escaped = _run(["report", str(path), "--model", str(model), "-o", str(tmp_path / "r.html")], capsys)
    said = err.strip().splitlines()
    assert code == 2 and escaped is None and len(said) == 2 and "misses 1 row" in said[0]
    assert "t.csv, row 46, column meas_y: " in said[1] and not (tmp_path / "r.html").exists()
    # diagnose --model said "pose 44" (its place in the call), after the whole diagnosis
    code, err, escaped = _run(["diagnose", str(path), "--model", str(model)], capsys)
    assert code == 2 and escaped is None and len(err.strip().splitlines()) == 1   # the model read first
    assert "t.csv, row 46, column meas_y: " in err and "pose 44" not in err


def test_apply_keep_going_writes_a_refused_pose_as_nan_and_counts_it(tmp_path, capsys) -> None:
    """--keep-going: the poses the model refuses (outside its box, a zero quaternion) are written as nan and
    counted with their rows, every other pose as a plain apply of the table without them
    writes it, and the metrics are over the poses corrected; all refused is an error."""
    from posecorr.controller.apply import apply_file

    model = _bounded_model(tmp_path)
    path, kept = tmp_path / "t.csv", tmp_path / "kept.csv"
    write_table(_table(60, seed=6), path)
    lines = path.read_text().splitlines()
    for row in (46, 50):          # file rows (the header is row 1)
        cells = lines[row - 1].split(",")
        cells[2] = "5.0"
        lines[row - 1] = ",".join(cells)
    header = lines[0].split(",")
    cells = lines[52 - 1].split(",")  # tracking lost: the log's zero quaternion
    for column in ("meas_qw", "meas_qx", "meas_qy", "meas_qz"):
        cells[header.index(column)] = "0"
    lines[52 - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    kept.write_text("\n".join(line for i, line in enumerate(lines, 1) if i not in (46, 50, 52)) + "\n")
    got = apply_file(model, path, tmp_path / "out.csv", chunk_rows=7, keep_going=True)
    plain = apply_file(model, kept, tmp_path / "plain.csv")
    assert got["refused"]["count"] == 3 and got["refused"]["rows"] == [46, 50, 52]
    assert got["refused"]["first"].startswith(f"{path}, row 46, column meas_y: ")
    out, want = read_csv_columns(tmp_path / "out.csv"), read_csv_columns(tmp_path / "plain.csv")
    refused = ~np.isfinite(out["corr_x"])
    assert list(np.flatnonzero(refused) + 2) == [46, 50, 52]
    for column in ("corr_x", "corr_y", "corr_z", "corr_qw", "corr_qx", "corr_qy", "corr_qz"):
        np.testing.assert_array_equal(out[column][~refused], want[column])
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        assert got["corrected"][key] == pytest.approx(plain["corrected"][key], rel=1e-12)
    assert main(["apply", str(model), str(path), "-o", str(tmp_path / "o.csv"), "--keep-going"]) == 0
    shown = capsys.readouterr().out.splitlines()
    assert shown[0].startswith("57 of 60 poses corrected") and shown[1].startswith(
        "3 poses refused by the model, written as nan (rows 46, 50, 52); the metrics are over the others")
    with pytest.raises(TableError, match="row 52, column meas_qw..meas_qz: a zero quaternion .*; a tracker that lost "
                                         "tracking writes zeros: --keep-going writes such a pose as nan and goes on$"):
        apply_file(model, path, tmp_path / "stopped.csv")   # without --keep-going the table's fault, as before

    every = tmp_path / "every.csv"
    every.write_text("\n".join([lines[0], lines[45], lines[49]]) + "\n")
    with pytest.raises(TableError, match=r"row 2, column meas_y: .*\(metadata input_bounds\); --keep-going writes "
                                         "each pose the model refuses as nan and goes on$"):
        apply_file(model, every, tmp_path / "stopped.csv")   # the way on, said where apply stops
    with pytest.raises(TableError, match="the model refused every pose; the first: .*row 2, column meas_y"):
        apply_file(model, every, tmp_path / "none.csv", keep_going=True)
    assert not (tmp_path / "none.csv").exists()


def test_apply_keep_going_passes_a_lost_measured_cell_to_the_model(tmp_path) -> None:
    """A log that writes an empty cell or nan where tracking was lost stopped apply even with
    --keep-going ('empty value, expected a number'): now the model refuses that pose alone.
    A reference cell, or a measured cell of text, is still the table's fault."""
    from posecorr.controller.apply import apply_file

    model = _bounded_model(tmp_path)
    path = tmp_path / "t.csv"
    write_table(_table(20, seed=6), path)
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    for row, column, text in ((5, "meas_x", ""), (9, "meas_qz", "NaN"), (12, "meas_y", " nan ")):
        cells = lines[row - 1].split(",")
        cells[header.index(column)] = text
        lines[row - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    got = apply_file(model, path, tmp_path / "out.csv", keep_going=True)
    assert got["refused"]["count"] == 3 and got["refused"]["rows"] == [5, 9, 12]
    assert got["refused"]["first"] == (f"{path}, row 5, column meas_x: {model}: non-finite input: x is not finite "
                                       "(expected a finite number)")
    with pytest.raises(TableError, match="row 5, column meas_x: empty value, expected a number"):
        apply_file(model, path, tmp_path / "stopped.csv")
    for column, text, said in (("ref_x", "", "empty value"), ("meas_x", "lost", "expected a number, got 'lost'")):
        cells = lines[6].split(",")
        cells[header.index(column)] = text
        path.write_text("\n".join(lines[:6] + [",".join(cells)] + lines[7:]) + "\n")
        with pytest.raises(TableError, match=f"row 7, column {column}: {said}"):
            apply_file(model, path, tmp_path / "stopped.csv", keep_going=True)


def test_apply_marks_the_poses_a_model_was_fitted_on_as_in_sample(tmp_path, capsys) -> None:
    """On the table a fit saw, apply's corrected figures are in-sample: it says so and puts
    the fit's held-out figures (as `fit --json` printed them) beside them; with one cell a
    nanometre off, the figures are that table's own, unmarked. Chunks do not matter."""
    from posecorr.controller.apply import apply_file

    session = tmp_path / "session.csv"
    write_table(_table(12, seed=3), session)
    model = tmp_path / "m.onnx"
    capsys.readouterr()
    assert main(["fit", str(session), "--effects", "station,mount", "--method", "none", "--cv", "loo",
                 "--json", "-o", str(model)]) == 0
    fitted = json.loads(capsys.readouterr().out)
    held_out, rigid = fitted["cv"], fitted["baseline"]
    for chunk_rows in (5, 1000):
        got = apply_file(model, session, tmp_path / f"c{chunk_rows}.csv", chunk_rows=chunk_rows)
        assert got["in_sample"] is True and got["held_out"]["source"] == "cv"
        assert got["held_out"]["rigid"]["name"] == rigid["name"]
        for key in ("rmse_pos", "rmse_rot", "rmse_total"):
            assert got["held_out"][key] == pytest.approx(held_out[key], rel=1e-12)
            assert got["held_out"]["rigid"][key] == pytest.approx(rigid[key], rel=1e-12)
    assert main(["apply", str(model), str(session), "-o", str(tmp_path / "c.csv")]) == 0
    shown = capsys.readouterr().out
    assert "corrected (in-sample)" in shown and "held out (the fit's cross-validation)" in shown
    assert f"{held_out['rmse_pos'] * 1e3:.4g}" in shown.split("held out")[1]
    floor = next(line for line in shown.splitlines() if line.startswith("the best rigid fit"))
    assert floor.startswith(f"the best rigid fit ({rigid['name']}), held out alike")
    assert floor.split()[-3] == f"{rigid['rmse_pos'] * 1e3:.4g}"

    lines = session.read_text().splitlines()
    column = lines[0].split(",").index("ref_x")
    cells = lines[4].split(",")
    cells[column] = repr(float(cells[column]) + 1e-9)
    lines[4] = ",".join(cells)
    other = tmp_path / "other.csv"
    other.write_text("\n".join(lines) + "\n")
    got = apply_file(model, other, tmp_path / "o.csv")
    assert got["in_sample"] is False and got["held_out"] is None
    assert main(["apply", str(model), str(other), "-o", str(tmp_path / "o2.csv")]) == 0
    assert "in-sample" not in capsys.readouterr().out


def test_apply_knows_the_fits_poses_in_another_order(tmp_path, capsys) -> None:
    """The table a fit saw, sorted (a spreadsheet, `sort`): apply showed plain "corrected", as
    on poses the model never saw. Its poses are the fit's (the model's training_set_digest):
    in-sample, said so, the fit's held-out figures beside them; one cell off, they are not."""
    from posecorr.controller.apply import apply_file

    table = _table(12, seed=3)
    session, model = tmp_path / "session.csv", tmp_path / "m.onnx"
    write_table(table, session)
    assert main(["fit", str(session), "--effects", "station,mount", "--method", "none", "--cv", "loo",
                 "-o", str(model)]) == 0
    reordered = tmp_path / "reordered.csv"
    write_table(table.subset(np.argsort(table.meas_p[:, 0])), reordered)
    got = apply_file(model, reordered, tmp_path / "r.csv")
    assert got["in_sample"] is True and got["fitted_on"] == "training-reordered"
    assert got["held_out"] == apply_file(model, session, tmp_path / "s.csv")["held_out"]
    capsys.readouterr()
    assert main(["apply", str(model), str(reordered), "-o", str(tmp_path / "r2.csv")]) == 0
    shown = capsys.readouterr().out
    assert "corrected (in-sample)" in shown and "held out (the fit's cross-validation)" in shown
    assert "was fitted on these poses, in another order (its training_set_digest)" in shown

    moved = table.subset(np.arange(table.n)[::-1])
    moved.ref_p = moved.ref_p.copy()
    moved.ref_p[4, 0] += 1e-9
    write_table(moved, reordered)
    got = apply_file(model, reordered, tmp_path / "m.csv")
    assert got["in_sample"] is False and got["fitted_on"] is None and got["held_out"] is None


def test_a_time_model_on_its_poses_at_other_times_is_not_in_sample(tmp_path, capsys) -> None:
    """A model with drift takes the times: its poses with t in minutes, not seconds, are other
    data to it. The digest left t out, so apply and report called them the fit's own and its
    corrections in-sample; a model without time still matches whatever the t column holds."""
    from posecorr import Corrector
    from posecorr.controller.apply import apply_file
    from posecorr.data import read_table
    from posecorr.simulate import simulate_session

    session, minutes = tmp_path / "session.csv", tmp_path / "minutes.csv"
    table = simulate_session(3, robot="ur5e", n=50, duration=2000.0,
                             extra={"drift": np.array([0.004, -0.002, 0.003, 1800.0])}).table
    write_table(table, session)
    write_table(replace(table, extras={**table.extras, "t": table.extras["t"] / 60.0}), minutes)
    assert read_table(minutes).time() is not None
    for effects, takes_time in (("station,mount,drift", True), ("station,mount", False)):
        model = tmp_path / f"{takes_time}.onnx"
        assert main(["fit", str(session), "--effects", effects, "--method", "none", "--cv", "loo", "-o",
                     str(model)]) == 0
        assert Corrector(model).takes_time is takes_time
        assert apply_file(model, session, tmp_path / "s.csv")["in_sample"] is True
        got = apply_file(model, minutes, tmp_path / "m.csv", keep_going=True)
        assert got["in_sample"] is (not takes_time), effects
    capsys.readouterr()


def test_apply_names_the_table_a_fit_with_a_test_split_read(tmp_path, capsys) -> None:
    """A fit with the fixed test split trains on 85 % of its table: apply on that table was
    shown as plain "corrected" (better than the test split's figure, unmarked). It is now "the
    fit's table", mostly in-sample, with the fit's test-split figures beside it; the training
    rows alone are in-sample; another table is neither."""
    from posecorr.controller.apply import apply_file
    from posecorr.simulate import simulate
    from posecorr.train.protocol import split_indices

    table = simulate(3, seed=5).table.subset(np.arange(300))
    session = tmp_path / "session.csv"
    write_table(table, session)
    model = tmp_path / "m.onnx"
    capsys.readouterr()
    assert main(["fit", str(session), "--method", "pmc", "--json", "-o", str(model)]) == 0
    fitted = json.loads(capsys.readouterr().out)
    got = apply_file(model, session, tmp_path / "c.csv")
    assert got["in_sample"] is True and got["fitted_on"] == "table" and got["held_out"]["source"] == "test"
    assert got["held_out"]["rmse_pos"] == pytest.approx(fitted["test"]["rmse_pos"], rel=1e-12)
    assert main(["apply", str(model), str(session), "-o", str(tmp_path / "c2.csv")]) == 0
    shown = capsys.readouterr().out
    assert "corrected (the fit's table)" in shown and "held out (the fit's test split)" in shown
    assert "fitted on this table's training rows, its test split held out" in shown
    train, val, _ = split_indices(table.n, 0)
    trained = tmp_path / "trained.csv"
    write_table(table.subset(np.sort(np.concatenate([train, val]))), trained)
    got = apply_file(model, trained, tmp_path / "t.csv")
    assert got["fitted_on"] == "training" and got["in_sample"] is True
    write_table(table.subset(np.arange(250)), tmp_path / "part.csv")
    got = apply_file(model, tmp_path / "part.csv", tmp_path / "p.csv")
    assert got["fitted_on"] is None and got["in_sample"] is False
    # the table, and its training rows, in another order: the same poses
    write_table(table.subset(np.arange(table.n)[::-1]), tmp_path / "reversed.csv")
    got = apply_file(model, tmp_path / "reversed.csv", tmp_path / "v.csv")
    assert got["fitted_on"] == "table-reordered" and got["in_sample"] is True and got["held_out"]["source"] == "test"
    assert main(["apply", str(model), str(tmp_path / "reversed.csv"), "-o", str(tmp_path / "v2.csv")]) == 0
    assert "the table in another order (its fitted_table_set_digest)" in capsys.readouterr().out
    write_table(table.subset(np.concatenate([train, val])[::-1]), trained)
    assert apply_file(model, trained, tmp_path / "t2.csv")["fitted_on"] == "training-reordered"


def read_csv_columns(path: Path) -> dict[str, np.ndarray]:
    import csv

    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    out = {}
    for i, name in enumerate(rows[0]):
        try:
            out[name] = np.array([float(r[i]) for r in rows[1:]])
        except ValueError:
            out[name] = np.array([r[i] for r in rows[1:]], dtype=object)
    return out


# --- the command line around the verbs -----------------------------------------------------------

def test_info_escapes_control_characters_from_metadata(tmp_path, capsys) -> None:
    import onnx

    model = onnx.load(MODEL)
    entry = model.metadata_props.add()
    entry.key, entry.value = "note\x1b]0;pwned\x07", "\x1b[2J\x1b[31mred\u202e"
    path = tmp_path / "m.onnx"
    onnx.save(model, path)
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\u202e" not in out and "\x07" not in out
    assert "\\x1b[2J\\x1b[31mred\\u202e" in out
    assert main(["info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["note\x1b]0;pwned\x07"] == "\x1b[2J\x1b[31mred\u202e"


def test_a_closed_pipe_and_a_numpy_only_install_give_one_line(tmp_path) -> None:
    import subprocess

    command = f"{shlex.quote(sys.executable)} -m posecorr.cli info {shlex.quote(str(MODEL))} | head -1"
    p = subprocess.run(command, shell=True, capture_output=True, text=True, timeout=120)
    assert p.stdout.count("\n") == 1 and "Traceback" not in p.stderr and p.stderr == ""
    # Block the train extra's modules as a numpy-only install lacks them.
    write_table(_table(20), tmp_path / "d.csv")
    script = """
import sys
class Missing:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in sys.argv[1].split(","):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Missing())
from posecorr.cli import main
sys.exit(main(sys.argv[2:]))
"""
    train = "onnxruntime,torch,scipy,sklearn,onnx,matplotlib,tqdm,ray"
    for blocked, argv, needs in [
            (train, ["apply", str(MODEL), str(tmp_path / "d.csv"), "-o", str(tmp_path / "o.csv"),
                     "--backend", "onnxruntime"], "onnxruntime"),
            (train, ["fit", str(tmp_path / "d.csv"), "-o", str(tmp_path / "m.onnx")], "posecorr[train]"),
            ("ray", ["sweep", str(tmp_path / "d.csv"), "--ray", "auto", "--no-mlp"], "ray")]:
        p = subprocess.run([sys.executable, "-c", script, blocked, *argv], capture_output=True, text=True,
                           timeout=120)
        lines = p.stderr.strip().splitlines()
        assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
        assert "is not installed" in lines[0] and "pip install" in lines[0]
        assert needs in lines[0]
    assert main(["apply", str(MODEL), str(tmp_path / "d.csv"), "-o", str(tmp_path / "o.csv")]) == 0


# --- the shim's misuse and its models (issue 31) ------------------------------------------

@pytest.mark.parametrize("backend", ["c", "onnxruntime"])
def test_the_shim_refuses_a_fifo_and_a_folder_as_the_model(tmp_path, backend) -> None:
    """In the command line's words, at once (a FIFO without writer blocked the load forever:
    a subprocess, so that a regression fails on its timeout and does not hang the suite)."""
    import subprocess

    os.mkfifo(tmp_path / "m.onnx")
    code = ("import sys\nfrom posecorr.controller.runtime import Corrector, PoseCorrError\n"
            "try:\n    Corrector(sys.argv[1], backend=sys.argv[2])\n"
            "except PoseCorrError as exc:\n    print(exc)\n")
    run = subprocess.run([sys.executable, "-c", code, str(tmp_path / "m.onnx"), backend],
                         capture_output=True, text=True, timeout=120)
    assert run.stdout.strip() == f"{tmp_path / 'm.onnx'}: is a FIFO, expected a file", run
    with pytest.raises(PoseCorrError, match=r": is a folder, expected a file$"):
        Corrector(tmp_path, backend=backend)


@pytest.mark.parametrize("backend", ["c", "onnxruntime"])
def test_the_shim_refuses_complex_poses_and_calls_after_close(backend) -> None:
    pose = _table(1).measured[0]
    corrector = Corrector(MODEL, backend=backend)
    for bad in (pose.astype(complex), pose[None].astype(complex), pose.astype(str)):
        with pytest.raises(ValueError, match="poses must be real numbers"):
            corrector.correct(bad)
    corrector.close()
    for args in ((pose,), (pose[None],)):
        with pytest.raises(PoseCorrError, match=r"pmc-zhou.onnx: the Corrector is closed"):
            corrector.correct(*args)
    corrector.close()  # twice is harmless


@pytest.mark.parametrize("max_batch", [-1, 0, 4097, 2.5, True, "16"])
def test_the_shim_refuses_a_max_batch_out_of_range(max_batch) -> None:
    with pytest.raises(ValueError, match=r"max_batch must be an integer from 1 to 4096"):
        Corrector(MODEL, max_batch=max_batch)


def test_the_shim_keeps_every_max_batch_in_range() -> None:
    poses = _table(40).measured
    want = Corrector(MODEL).correct(poses)
    for max_batch in (1, 16, 4096):
        np.testing.assert_array_equal(Corrector(MODEL, max_batch=max_batch).correct(poses), want)


def test_a_partial_left_by_a_killed_run_is_removed_by_the_next(tmp_path, capsys) -> None:
    """SIGKILL leaves `replaced`'s hidden .partial (no clean-up runs); the next run on the
    same target removes it and says so; a live process' partial is left alone."""
    import signal
    import subprocess

    from posecorr.safeio import replaced

    target = tmp_path / "demo"
    code = ("import sys, time\nfrom posecorr.safeio import replaced\n"
            "with replaced(sys.argv[1]) as fresh:\n    fresh.mkdir()\n    (fresh / 'a.txt').write_text('x')\n"
            "    print(fresh, flush=True)\n    time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(target)], stdout=subprocess.PIPE, text=True)
    stale = Path(proc.stdout.readline().strip())
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert stale.is_dir() and stale.name.startswith(".demo.") and ".partial" in stale.name
    live = tmp_path / f".demo.{os.getpid()}.0123abcd.partial"
    live.mkdir()
    with replaced(target) as fresh:
        fresh.mkdir()
    assert target.is_dir() and not stale.exists() and live.exists()
    assert f"{stale}: removed, left by an interrupted run (process {proc.pid}, now gone)" in capsys.readouterr().err


def test_a_table_longer_than_a_fit_takes_is_refused_early_or_drawn(tmp_path, capsys, monkeypatch) -> None:
    """Past FIT_ROWS_MAX rows `fit` stops reading and refuses, naming how to reduce the
    table (no model, no ledger line); --subsample N fits an even draw of N rows (the limit
    made small here: the figures on 10^6 rows are bench/fit_long.py's)."""
    from posecorr.cli import fit as fit_verb
    from posecorr.data import TooManyRows

    monkeypatch.setattr(fit_verb, "FIT_ROWS_MAX", 60)
    data, out = tmp_path / "d.csv", tmp_path / "m.onnx"
    write_table(_table(200), data)
    with pytest.raises(TooManyRows, match=r"d.csv: more than 60 data rows$"):
        read_table(data, max_rows=60)
    code, err, escaped = _run(["fit", str(data), "-o", str(out)], capsys)
    assert code == 2 and escaped is None and err.count("\n") == 1, err
    assert "more than 60 rows" in err and "posecorr ingest" in err and "--subsample 60" in err
    assert not out.exists() and not (tmp_path / "d.csv.ledger.jsonl").exists()
    code, err, escaped = _run(["fit", str(data), "-o", str(out), "--subsample", "50", "--json"], capsys)
    assert code == 0 and escaped is None, err
    drawn, keep = read_table(data).draw(50, 0)
    assert drawn.n == 50 and len(set(keep)) == 50 and np.all(np.diff(keep) > 0)
    ledger = json.loads((tmp_path / "d.csv.ledger.jsonl").read_text().splitlines()[0])
    assert ledger["model"] == out.name      # named from the data's directory, which holds both


def test_the_c_loader_says_a_folder_cannot_be_read(tmp_path) -> None:
    """pc_load_file itself (C callers, without the shim's check): a folder opens and seeks
    on glibc, its size reading as LONG_MAX; it was 'out of memory reading', now IO."""
    import ctypes

    from posecorr.controller import runtime

    lib = runtime.load_library()
    handle, err = ctypes.c_void_p(), runtime._Error()
    status = lib.pc_load_file(os.fsencode(tmp_path), None, ctypes.byref(handle), ctypes.byref(err))
    assert status == 2 and handle.value is None  # PC_ERR_IO
    assert err.message.decode() == f"cannot read '{tmp_path}': is a folder, expected a regular file"


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="no /proc (Linux's)")
def test_the_c_loader_does_not_call_a_generated_file_empty() -> None:
    """/proc's files are regular, say 0 bytes and hold more: pc_load_file read the size and
    said 'truncated file at byte 0 (empty)' of a file that is not."""
    import ctypes

    from posecorr.controller import runtime

    lib = runtime.load_library()
    handle, err = ctypes.c_void_p(), runtime._Error()
    status = lib.pc_load_file(b"/proc/self/status", None, ctypes.byref(handle), ctypes.byref(err))
    assert status == 2 and handle.value is None  # PC_ERR_IO
    assert err.message.decode() == ("cannot read '/proc/self/status': it holds more than the 0 bytes its size says "
                                    "(a file that changes, or one the system generates)")


def test_the_c_loader_refuses_a_fifo_at_once(tmp_path) -> None:
    """pc_load_file itself (C callers, without the shim's check): fopen of a FIFO without a
    writer waited forever; now PC_ERR_IO at once (a subprocess with a timeout, so that a
    regression fails and does not hang the suite). posecorr-run and the shim refuse it in
    the same one line, the command line's words."""
    import subprocess

    fifo = tmp_path / "m.onnx"
    os.mkfifo(fifo)
    code = ("import ctypes, os, sys\nfrom posecorr.controller import runtime\n"
            "lib = runtime.load_library()\nhandle, err = ctypes.c_void_p(), runtime._Error()\n"
            "st = lib.pc_load_file(os.fsencode(sys.argv[1]), None, ctypes.byref(handle), ctypes.byref(err))\n"
            "print(st, handle.value, err.message.decode())\n")
    run = subprocess.run([sys.executable, "-c", code, str(fifo)], capture_output=True, text=True, timeout=60)
    assert run.stdout.strip() == f"2 None cannot read '{fifo}': is a FIFO, expected a regular file", run
    tool = Path(sys.executable).parent / "posecorr-run"
    run = subprocess.run([str(tool), str(fifo)], input="0,0,0,1,0,0,0\n", capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 1 and run.stdout == "", run
    # the shim's line (test_the_shim_refuses_a_fifo_and_a_folder_as_the_model), after the tool's name
    assert run.stderr.splitlines() == [f"posecorr-run: {fifo}: is a FIFO, expected a file"], run


def test_a_row_of_empty_cells_is_named_and_kept_in_place(tmp_path, capsys) -> None:
    """A spreadsheet exports a deleted row as a line of commas: it was skipped without a word,
    and apply's output lost the line, so matching its lines to the input's was off by one
    from there. It is named now (one warning) and written back where it stood, as a blank
    line is."""
    from posecorr.controller.apply import apply_file
    from posecorr.data import read_table

    t = _table(9, seed=5)
    plain = tmp_path / "plain.csv"
    write_table(t, plain)
    lines = plain.read_text().splitlines()
    empty = "," * (lines[0].count(","))
    path = tmp_path / "gaps.csv"
    path.write_text("\n".join(lines[:3] + [empty] + lines[3:6] + [""] + lines[6:]) + "\n")
    capsys.readouterr()
    assert read_table(path).n == t.n
    assert capsys.readouterr().err.strip().splitlines() == [
        f"posecorr: warning: {path}: row 4 has every cell empty: no pose read there"]
    apply_file(MODEL, plain, tmp_path / "plain_out.csv")
    for chunk_rows in (2, 1000):
        apply_file(MODEL, path, tmp_path / "out.csv", chunk_rows=chunk_rows)
        want = (tmp_path / "plain_out.csv").read_text().splitlines()
        assert (tmp_path / "out.csv").read_text().splitlines() == want[:3] + [empty] + want[3:6] + [""] + want[6:]


def test_apply_copies_comment_lines_where_they_stood(tmp_path, capsys) -> None:
    """The corrected table is the plain one's with the input's comment lines (before the
    header, among the poses, after them) at the same places: nothing of the file is lost, and
    the chunks' edges do not move them."""
    from posecorr.controller.apply import apply_file

    t = _table(9, seed=5)
    plain = tmp_path / "plain.csv"
    write_table(t, plain)
    lines = plain.read_text().splitlines()
    commented = lines[:3] + ["# after pose 2", "# and another"] + lines[3:7] + ["#" + lines[7]] + lines[8:]
    path = tmp_path / "commented.csv"
    path.write_text("\n".join(["# preamble"] + commented + ["# end"]) + "\n")
    notes = ["# preamble", "# after pose 2", "# and another", "#" + lines[7], "# end"]
    apply_file(MODEL, plain, tmp_path / "plain_out.csv")
    for chunk_rows in (2, 3, 1000):
        apply_file(MODEL, path, tmp_path / "out.csv", chunk_rows=chunk_rows)
        want = (tmp_path / "plain_out.csv").read_text().splitlines()
        del want[7]   # the pose commented out is no pose of the output
        got = (tmp_path / "out.csv").read_text().splitlines()
        assert [x for x in got if not x.startswith("#")] == want
        assert [x for x in got if x.startswith("#")] == notes
        assert got.index("# after pose 2") == 4 and got[0] == "# preamble" and got[-1] == "# end"


def test_apply_keeps_the_inputs_line_endings(tmp_path) -> None:
    """A table with Windows line endings (CRLF) gives a corrected table with them, on every
    line, a quoted cell's own line break included: byte for byte the LF table's output with
    each LF turned CRLF."""
    from posecorr.controller.apply import apply_file

    plain = tmp_path / "plain.csv"
    write_table(_table(6, seed=3), plain)
    lines = [x for x in plain.read_text().splitlines() if not x.startswith("#")]
    lines = [lines[0] + ",note"] + [x + (',"two\nlines"' if i == 2 else ",one") for i, x in enumerate(lines[1:])]
    text = "# a session\n" + "\n".join(lines) + "\n# end\n"
    unix, windows = tmp_path / "unix.csv", tmp_path / "windows.csv"
    unix.write_bytes(text.encode())
    windows.write_bytes(text.replace("\n", "\r\n").encode())
    apply_file(MODEL, unix, tmp_path / "unix_out.csv")
    apply_file(MODEL, windows, tmp_path / "windows_out.csv")
    want = (tmp_path / "unix_out.csv").read_bytes()
    assert b"\r" not in want and b'"two\nlines"' in want
    assert (tmp_path / "windows_out.csv").read_bytes() == want.replace(b"\n", b"\r\n")


def test_apply_gives_no_improvement_over_the_offset_of_unregistered_frames(tmp_path, capsys) -> None:
    """On a table in the tracker's own frame (the reference turned 90 deg and moved 2 m),
    raw measures the frames' offset: apply gives no improvement over it, says so, and names the
    Kabsch fit it judged by, whose figure equals scipy's own alignment of the same positions
    (streamed in chunks of 4 poses alike).
    On registered frames the improvements are raw / corrected, as before."""
    t = _table(30, seed=2)
    turn = Rotation.from_euler("z", 90, degrees=True)
    moved = replace(t, ref_p=turn.apply(t.ref_p) + [2.0, 0.5, 0.0], ref_q=(turn * Rotation.from_quat(
        t.ref_q, scalar_first=True)).as_quat(scalar_first=True))
    registered, unregistered = tmp_path / "registered.csv", tmp_path / "unregistered.csv"
    write_table(t, registered)
    write_table(moved, unregistered)

    near = json.loads(_json_of(["apply", str(MODEL), str(registered), "-o", str(tmp_path / "a.csv")], capsys))
    raw, corrected = near["raw"], near["corrected"]
    assert near["unregistered"] is False
    assert corrected["improvement_pos"] == pytest.approx(raw["rmse_pos"] / corrected["rmse_pos"], rel=1e-12)

    far = json.loads(_json_of(["apply", str(MODEL), str(unregistered), "-o", str(tmp_path / "b.csv")], capsys))
    assert far["unregistered"] is True and far["raw"]["rmse_pos"] > 1.0
    assert [far["corrected"][f"improvement_{k}"] for k in ("pos", "rot", "total")] == [None] * 3
    centred_m, centred_r = t.meas_p - t.meas_p.mean(axis=0), moved.ref_p - moved.ref_p.mean(axis=0)
    aligned, _ = Rotation.align_vectors(centred_r, centred_m)
    want = np.sqrt(np.mean(np.sum((aligned.apply(centred_m) - centred_r) ** 2, axis=1)))
    assert far["kabsch_rmse_pos"] == pytest.approx(want, rel=1e-6)
    from posecorr.controller.apply import apply_file   # its sums, chunk by chunk, give the same fit

    chunked = apply_file(MODEL, unregistered, tmp_path / "c.csv", chunk_rows=4)
    assert chunked["kabsch_rmse_pos"] == pytest.approx(far["kabsch_rmse_pos"], rel=1e-9)

    assert main(["apply", str(MODEL), str(unregistered), "-o", str(tmp_path / "b.csv")]) == 0
    out = capsys.readouterr().out
    assert "Kabsch fit of the positions, same poses (in-sample)" in out
    assert "the frames are unregistered (raw rmse_pos above 10x a Kabsch fit's and 100 mm)" in out


def _json_of(argv: list[str], capsys) -> str:
    capsys.readouterr()
    assert main(argv + ["--json"]) == 0
    return capsys.readouterr().out
