"""`sweep --ray` on a Ray cluster of two nodes started here (`ray start --head`, then a second
`ray start --address`), each node one CPU and a resource of its own: the tables equal the
local run's, both nodes ran runs, and a worker node killed mid-sweep costs no finished run.

Each node is started in a session of its own: its raylet and agents are that session's, its
workers the raylet's children. Stopping a node is killing those processes by id, never
`ray stop`, which ends every Ray process of the machine, another user's cluster included.
Nothing here leaves the machine: usage statistics are off and the dashboard's web UI is not
started (its ports, like every other, are free ones picked here).
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from posecorr.cli import main
from posecorr.data import write_table
from posecorr.train.protocol import build_grid, run_sweep

from test_protocol import synthetic_table

pytest.importorskip("ray", reason="make test installs posecorr[ray]")

RAY = Path(sys.executable).with_name("ray")
ENV = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
# Six networks of about half a second each and six PMC runs: long enough that a node is caught
# running one, short enough for the suite.
REPEATS = 3
RUNS = 4 * REPEATS
GRID = ["--representations", "zhou,R", "--activations", "tansig", "--architectures", "20", "--trainers", "lm",
        "--epochs", "20", "--repeats", str(REPEATS)]
TASK_TITLE = "ray::_run_on_node"  # the title Ray gives a worker process running a sweep run
DEADLINE = 120.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Node:
    """One `ray start` with its own temporary folder (under /tmp: Ray's socket paths, which
    live inside it, must fit in 107 bytes) and its own ports. ``wait`` for it to be up."""

    def __init__(self, *args: str) -> None:
        self.temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")
        self.args = args
        command = [str(RAY), "start", "--temp-dir", self.temp, "--num-cpus", "1", "--disable-usage-stats",
                   "--min-worker-port", "0", "--max-worker-port", "0",
                   "--dashboard-agent-listen-port", str(_free_port()), *args]
        self.proc = subprocess.Popen(command, env=ENV, start_new_session=True, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)

    def wait(self) -> "Node":
        try:
            out, _ = self.proc.communicate(timeout=DEADLINE)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"`ray start {' '.join(self.args)}` did not return in {DEADLINE:.0f} s") from None
        assert self.proc.returncode == 0, f"`ray start {' '.join(self.args)}` failed:\n{out[-3000:]}"
        return self

    def processes(self) -> dict[int, str]:
        """pid -> command line of the node's live processes: those of its session (raylet,
        agents) and their descendants (the workers, each in a process group of its own)."""
        table = {}
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except (OSError, IndexError):
                continue
            if stat[0] != "Z":
                table[int(entry.name)] = (int(stat[1]), int(stat[3]), cmdline.strip())
        found = {pid for pid, (_, session, _) in table.items() if session == self.proc.pid}
        while grown := {pid for pid, (parent, _, _) in table.items() if parent in found} - found:
            found |= grown
        return {pid: table[pid][2] for pid in found}

    def node_id(self) -> str:
        for cmdline in self.processes().values():
            for arg in cmdline.split():
                if arg.startswith("--node_id="):
                    return arg.split("=", 1)[1]
        raise AssertionError(f"no raylet runs in the node started by `ray start {' '.join(self.args)}`")

    def busy(self) -> bool:
        return any(cmd.startswith(TASK_TITLE) for cmd in self.processes().values())

    def kill(self) -> None:
        for pid in self.processes():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def stop(self) -> None:
        """Kill the node's processes and wait until none is left; remove its folder."""
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)  # the session's group first: it needs no lookup
        except ProcessLookupError:
            pass
        if self.proc.poll() is None:
            self.proc.communicate()
        deadline = time.monotonic() + 30
        while (left := self.processes()) and time.monotonic() < deadline:
            self.kill()
            time.sleep(0.1)
        shutil.rmtree(self.temp, ignore_errors=True)
        assert not left, f"Ray processes outlived their node: {left}"


class Cluster:
    """A head node and a worker node; a worker node a test killed is replaced by a new one."""

    def __init__(self, head: Node, address: str) -> None:
        self.head, self.address, self.worker = head, address, None

    def live_worker(self) -> Node:
        if self.worker is None or not self.worker.processes():
            if self.worker is not None:
                self.worker.stop()
            self.worker = Node("--address", self.address, "--resources", '{"worker_node": 1}').wait()
        return self.worker


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("ray") / "d.csv"
    write_table(synthetic_table(), path)
    return path


@pytest.fixture(scope="module")
def head():
    port = _free_port()
    node = Node("--head", "--port", str(port), "--resources", '{"head_node": 1}', "--include-dashboard=false",
                "--dashboard-port", str(_free_port()))
    node.address = f"127.0.0.1:{port}"
    try:
        yield node
    finally:
        node.stop()


@pytest.fixture(scope="module")
def local(head, data):
    """The local run's tables (`sweep --json`'s output), one torch thread per run as on Ray;
    computed while the head node starts."""
    import torch

    from posecorr.data import read_table

    configs = build_grid("reduced", representations=["zhou", "R"], activations=["tansig"], trainers=["lm"],
                         architectures=["20"], options={"epochs": 20})
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return run_sweep(read_table(data), configs, repeats=REPEATS, workers=1, progress=False).to_json()
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def cluster(head, local):
    cluster = Cluster(head.wait(), head.address)
    try:
        yield cluster
    finally:
        if cluster.worker is not None:
            cluster.worker.stop()


def _start_sweep(data: Path, store: Path, address: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "posecorr.cli", "sweep", str(data), *GRID, "--store", str(store),
                             "--ray", address, "--json"], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def _finish(proc: subprocess.Popen) -> dict:
    try:
        out, err = proc.communicate(timeout=DEADLINE)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise AssertionError(f"the sweep did not end in {DEADLINE:.0f} s") from None
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out)


def _rows(store: Path) -> list[dict]:
    return [json.loads(line) for line in store.read_text().splitlines()]


def _assert_same_tables(got, want, where="") -> None:
    """The sweep's JSON, field by field. Both runs do each fit with one torch thread on this
    machine, so the sums come in the same order and the numbers should agree to the last bit;
    rel 1e-9 only keeps the comparison off that bit (a node of another CPU kind would round
    differently). Timings and the store's name are not results."""
    if isinstance(want, dict):
        keys = set(want) - {"seconds", "seconds_avg", "store"}
        assert keys == set(got) - {"seconds", "seconds_avg", "store"}, where
        for k in keys:
            _assert_same_tables(got[k], want[k], f"{where}.{k}")
    elif isinstance(want, list):
        assert len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want)):
            _assert_same_tables(g, w, f"{where}[{i}]")
    elif isinstance(want, float):
        assert got == pytest.approx(want, rel=1e-9, abs=1e-300), where
    else:
        assert got == want, where


def test_sweep_on_two_nodes_equals_the_local_run(cluster, data, local, tmp_path):
    worker = cluster.live_worker()
    store = tmp_path / "s.jsonl"
    got = _finish(_start_sweep(data, store, cluster.address))
    _assert_same_tables(got, local)
    rows = _rows(store)
    assert len(rows) == RUNS and len({(r["key"], r["repeat"]) for r in rows}) == RUNS
    assert {r["node"] for r in rows} == {cluster.head.node_id(), worker.node_id()}  # both nodes ran runs


def test_a_worker_node_killed_mid_sweep_costs_no_finished_run(cluster, data, local, tmp_path, capsys):
    worker = cluster.live_worker()
    store = tmp_path / "s.jsonl"
    proc = _start_sweep(data, store, cluster.address)
    deadline = time.monotonic() + DEADLINE
    # Kill the worker node once a run is stored and the node is running one.
    while not (store.exists() and store.stat().st_size and worker.busy()):
        assert proc.poll() is None, "the sweep ended before a run was stored with the worker node running one"
        assert time.monotonic() < deadline, "no run was stored with the worker node running one"
        time.sleep(0.02)
    worker.kill()
    before = store.read_bytes()
    got = _finish(proc)  # the run lost with the node was done again on the head
    _assert_same_tables(got, local)
    after = store.read_bytes()
    assert after.startswith(before)  # the runs stored before the kill stayed as they were
    rows = _rows(store)
    assert len(rows) == RUNS and len({(r["key"], r["repeat"]) for r in rows}) == RUNS  # none ran twice
    # Started again, the sweep finds every run in the store and runs none.
    capsys.readouterr()
    assert main(["sweep", str(data), *GRID, "--store", str(store), "--ray", cluster.address, "--json"]) == 0
    _assert_same_tables(json.loads(capsys.readouterr().out), local)
    assert store.read_bytes() == after
