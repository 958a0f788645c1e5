"""Killed mid-write (issue 14): `fit`, `apply` and `sweep` under SIGKILL and SIGTERM leave the
previous files intact, no temporary file and no orphan process.

Each verb runs as its own process through `posecorr.cli.main`, with one test-side hook that
pauses it at the worst moment and says so: `fit` inside the model file's write (content
written, not yet renamed), `apply` after its first chunk went out, `sweep` with two runs
stored and both workers busy. Then the process gets the signal.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr.cli import main, options
from posecorr.data import PoseTable, write_table

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "pmc-zhou.onnx"

# The hook, run as a script: argv = the posecorr arguments; the mode and the ready-file prefix
# come by the environment. The sweep's pool forks its workers after the patch below, so they
# inherit it; were they spawned, each would run this script's top (not its __main__ part).
HOOK = r"""
import os, sys, time
mode, ready = os.environ["HOOK_MODE"], os.environ["HOOK_READY"]

def pause():
    with open(f"{ready}.{os.getpid()}", "w") as f:
        f.write("paused")
    time.sleep(300)

if mode == "fit":
    real_fsync, folder = os.fsync, os.path.dirname(ready)
    def fsync(fd):
        real_fsync(fd)
        if os.readlink(f"/proc/self/fd/{fd}").startswith(folder):
            pause()
    os.fsync = fsync
elif mode == "apply":
    from posecorr.controller.runtime import Corrector
    real_correct, calls = Corrector.correct, []
    def correct(self, poses, t=None):
        calls.append(1)
        if len(calls) == 2:
            sys.stdout.flush()
            pause()
        return real_correct(self, poses, t=t)
    Corrector.correct = correct
elif mode == "sweep":
    import posecorr.train.protocol as protocol
    real_run = protocol.run_one
    def run_one(table, config, repeat, seed=0, threads=None):
        if repeat >= 4:
            pause()
        return real_run(table, config, repeat, seed, threads)
    protocol.run_one = run_one

if __name__ == "__main__":
    from posecorr.cli import main
    sys.exit(main(sys.argv[1:]))
"""


def _table(n: int, seed: int = 0) -> PoseTable:
    rng = np.random.default_rng(seed)
    p = np.array([0.0, -0.6, 0.5]) + rng.uniform(-0.1, 0.1, (n, 3))
    q = Rotation.from_euler("xyz", rng.uniform(-0.5, 0.5, (n, 3))).as_quat(scalar_first=True)
    return PoseTable(p + 0.003 + rng.normal(scale=3e-4, size=(n, 3)), q, p, q)


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file() and not p.name.startswith(("ready", "hook"))}


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            children.setdefault(ppid, []).append(int(entry.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _run_and_kill(mode: str, sig: int, folder: Path, argv: list[str], ready_count: int = 1,
                  until=lambda: True) -> tuple[subprocess.CompletedProcess | None, int, set[int], str]:
    ready = folder / "ready"
    hook = folder / "hook.py"
    hook.write_text(HOOK)
    proc = subprocess.Popen([sys.executable, str(hook), *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "HOOK_MODE": mode, "HOOK_READY": str(ready)})
    deadline = time.monotonic() + 240
    while not (len(list(folder.glob("ready.*"))) >= ready_count and until()):
        if proc.poll() is not None:
            raise AssertionError(f"{mode} ended before the pause: {proc.stderr.read()}")
        if time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"{mode} never reached the pause")
        time.sleep(0.05)
    family = _descendants(proc.pid)
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        for pid in family | {proc.pid}:  # leave nothing behind before failing
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.communicate()
        raise AssertionError(f"{mode} did not end within 120 s of the signal") from None
    for path in folder.glob("ready.*"):
        path.unlink()
    return proc, proc.returncode, family, err


def _assert_no_orphans(family: set[int]) -> None:
    deadline = time.monotonic() + 15
    while any(_alive(pid) for pid in family) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [pid for pid in family if _alive(pid)], "orphan processes left alive"


def _assert_ended(code: int, sig: int, err: str, verb: str) -> None:
    if sig == signal.SIGKILL:
        assert code == -signal.SIGKILL
    else:
        assert code == 143, err
        assert err.strip().splitlines()[-1].startswith(f"posecorr {verb}: terminated"), err
        assert "Traceback" not in err


SIGNALS = [pytest.param(signal.SIGKILL, id="SIGKILL"), pytest.param(signal.SIGTERM, id="SIGTERM")]


# verb: (rows and seed of the table, the complete run, the run that is killed, files the first leaves)
KILLED_WRITERS = {
    "fit": (80, 0, ["fit", "{data}", "-o", "{folder}/model.onnx", "--json"],
            ["fit", "{data}", "-o", "{folder}/model.onnx", "--method", "pmc", "--json"],
            {"d.csv", "model.onnx", "d.csv.ledger.jsonl"}),
    "apply": (40_000, 1, ["apply", str(MODEL), "{data}", "-o", "{folder}/out.csv", "--json"],
              ["apply", str(MODEL), "{data}", "-o", "{folder}/out.csv"], {"d.csv", "out.csv"}),
}


@pytest.mark.parametrize("sig", SIGNALS)
@pytest.mark.parametrize("verb", list(KILLED_WRITERS))
def test_killed_while_writing_leaves_the_previous_files(tmp_path, verb, sig, capsys) -> None:
    """fit killed while writing the model, apply killed mid-stream: the old model or output,
    the data and the ledger stay byte for byte, no partial file appears under any name."""
    rows, seed, complete, killed, files = KILLED_WRITERS[verb]
    data = tmp_path / "d.csv"
    write_table(_table(rows, seed=seed), data)

    def filled(args: list[str]) -> list[str]:
        return [a.format(data=data, folder=tmp_path) for a in args]

    assert main(filled(complete)) == 0
    before = _snapshot(tmp_path)
    assert files <= set(before)
    _, code, family, err = _run_and_kill(verb, sig, tmp_path, filled(killed))
    _assert_ended(code, sig, err, verb)
    assert _snapshot(tmp_path) == before
    _assert_no_orphans(family)


@pytest.mark.parametrize("sig", SIGNALS)
def test_sweep_killed_with_busy_workers(tmp_path, sig, capsys) -> None:
    data = tmp_path / "d.csv"
    write_table(_table(100, seed=2), data)
    store = tmp_path / "s.jsonl"
    args = ["sweep", str(data), "--no-mlp", "--representations", "zhou", "--store", str(store), "--json"]
    assert main([*args, "--repeats", "2", "--workers", "1"]) == 0
    previous = store.read_bytes()

    def stored() -> int:
        return store.read_bytes().count(b"\n")

    # Two workers; on a one-core machine the command caps --workers at 1, which runs in its
    # own process.
    workers = min(2, options.cores())
    _, code, family, err = _run_and_kill("sweep", sig, tmp_path, [*args, "--repeats", "6", "--workers", "2"],
                                         ready_count=workers, until=lambda: stored() == 4)
    _assert_ended(code, sig, err, "sweep")
    assert len(family) >= (workers if workers > 1 else 0)  # the pool's workers were there when the signal came
    _assert_no_orphans(family)
    text = store.read_bytes()
    assert text.startswith(previous)
    rows = [json.loads(line) for line in text.decode().splitlines()]
    assert sorted(r["repeat"] for r in rows) == [0, 1, 2, 3]  # what finished was kept
    capsys.readouterr()
    assert main([*args, "--repeats", "6", "--workers", "1"]) == 0  # resumes: two runs to go
    result = json.loads(capsys.readouterr().out)
    assert result["summary"][0]["runs"] == 6
    assert store.read_bytes().count(b"\n") == 6
