"""`posecorr ros2` over real rclpy and Fast DDS on loopback: the node runs as the CLI in its
own process, this test publishes the tracker's poses and listens to the corrected ones.
Every output must be the shim's correction of its pose, float32 bit for bit; none lost;
swaps between two messages; a corrupt file refused while the old model serves; SIGINT and
SIGTERM end the node cleanly. Each test has its own ROS domain, so parallel runs and other
nodes on the machine never cross."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="the ros2 extra is not installed (pip install 'posecorr[ros2]')")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402

from posecorr.controller.runtime import Corrector  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FIRST = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
SECOND = ROOT / "models" / "pmc-zhou.onnx"
POSECORR = str(Path(sys.executable).parent / "posecorr")


def _poses(n: int, seed: int) -> np.ndarray:
    """Poses inside the box both models were fitted in (their metadata input_bounds)."""
    from posecorr.controller.onnx_meta import read_info

    lo, hi = read_info(FIRST)["input_bounds"]
    assert read_info(SECOND)["input_bounds"] == [lo, hi]
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.hstack([rng.uniform(lo, hi, (n, 3)), q])


class Cell:
    """The node under test (a `posecorr ros2` process) and this test's own node."""

    def __init__(self, model: Path, domain: int, *extra: str) -> None:
        self.env = {**os.environ, "ROS_DOMAIN_ID": str(domain)}
        os.environ["ROS_DOMAIN_ID"] = str(domain)
        # the test publishes poses in the model's frame: no registration unless a test gives one
        registration = [] if "--registration" in extra else ["--registration", "none"]
        self.proc = subprocess.Popen([POSECORR, "ros2", str(model), "--reliable",
                                      "--diagnostics-period", "0.2", *registration, *extra],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     env=self.env)
        rclpy.init()
        self.node = rclpy.create_node("posecorr_test")
        qos = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_ALL)
        self.pub = self.node.create_publisher(PoseStamped, "/tracker/pose", qos)
        self.got: dict[int, PoseStamped] = {}
        self.diagnostics: list[dict[str, str]] = []
        self.node.create_subscription(PoseStamped, "/tracker/pose_corrected",
                                      lambda m: self.got.__setitem__(self.key(m), m), qos)
        self.node.create_subscription(
            DiagnosticArray, "/diagnostics",
            lambda m: self.diagnostics.append({kv.key: kv.value for kv in m.status[0].values}), 10)
        self.wait(lambda: self.pub.get_subscription_count() > 0 and
                  self.node.count_publishers("/tracker/pose_corrected") > 0 and self.diagnostics,
                  30, "the node never came up")

    @staticmethod
    def key(msg: PoseStamped) -> int:
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(self.node, timeout_sec=0.01)

    def wait(self, condition, seconds: float, what: str) -> None:
        end = time.monotonic() + seconds
        while not condition():
            if time.monotonic() > end:
                died = self.proc.poll() is not None
                pytest.fail(f"{what} ({len(self.got)} outputs so far"
                            + (f"; the node exited: {self.proc.stderr.read()}" if died else "") + ")")
            rclpy.spin_once(self.node, timeout_sec=0.02)

    def publish(self, poses: np.ndarray, first: int, rate_hz: float, at_index=None,
                frame: str = "tracker") -> None:
        """Publishes poses[k] with stamp (first + k) ms in `frame`, paced at rate_hz;
        at_index[k]() runs before pose k."""
        period, start = 1.0 / rate_hz, time.perf_counter()
        for k, p in enumerate(poses):
            if at_index and k in at_index:
                at_index[k]()
            msg = PoseStamped()
            ns = (first + k) * 1_000_000
            msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
            msg.header.frame_id = frame
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, p[:3])
            (msg.pose.orientation.w, msg.pose.orientation.x, msg.pose.orientation.y,
             msg.pose.orientation.z) = map(float, p[3:])
            self.pub.publish(msg)
            rclpy.spin_once(self.node, timeout_sec=0.0)
            wait = start + (k + 1) * period - time.perf_counter()
            if wait > 0:  # sleep, not spin: a spinning publisher starves the node of a core
                time.sleep(wait)

    def outputs(self, first: int, n: int) -> np.ndarray:
        rows = []
        for k in range(n):
            m = self.got[(first + k) * 1_000_000]
            o = m.pose
            rows.append([o.position.x, o.position.y, o.position.z, o.orientation.w,
                         o.orientation.x, o.orientation.y, o.orientation.z])
            assert m.header.frame_id == "base_link"
        return np.array(rows)

    def stop(self, sig=signal.SIGINT) -> tuple[int, str, str]:
        self.node.destroy_node()
        rclpy.shutdown()
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        out, err = self.proc.communicate(timeout=30)
        return self.proc.returncode, out, err


@pytest.fixture
def domain():
    """A ROS domain of this test's own (1..100): held under a lock file for the test's length,
    so that two suites on one host (CI beside a developer's run) never publish into one
    domain, where each would read the other's poses. Drawn from the pid and the clock, then
    the next free one."""
    import fcntl
    import tempfile

    start = os.getpid() * 7919 + time.monotonic_ns() // 1_000_000
    for k in range(100):
        number = 1 + (start + k) % 100
        lock = open(Path(tempfile.gettempdir()) / f"posecorr-ros-domain-{number}.lock", "w")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            continue
        try:
            yield number
        finally:
            lock.close()
        return
    pytest.fail("every ROS domain 1..100 is held by another test on this host")


def _shim(model: Path, poses: np.ndarray) -> np.ndarray:
    c = Corrector(model)
    return np.stack([c.correct(p) for p in poses])


def test_10000_poses_at_1khz_none_lost_each_the_shims_bits(domain, tmp_path):
    model = tmp_path / "model.onnx"
    shutil.copy(FIRST, model)
    cell = Cell(model, domain)
    try:
        x = _poses(10_000, seed=1)
        cell.publish(x, first=1000, rate_hz=1000.0)
        cell.wait(lambda: len(cell.got) == len(x), 30, "not every pose came back")
        np.testing.assert_array_equal(cell.outputs(1000, len(x)), _shim(FIRST, x))
        cell.wait(lambda: cell.diagnostics[-1]["poses_out"] == str(len(x)), 5, "diagnostics lag")
        d = cell.diagnostics[-1]
        assert (d["poses_in"], d["refused"], d["poses_per_generation"]) == ("10000", "0", "1:10000")
        print(f"1 kHz, 10,000 poses: node latency p50 {d['latency_p50_us']} us, "
              f"p99 {d['latency_p99_us']} us, max {d['latency_max_us']} us")
    finally:
        code, out, err = cell.stop()
    assert code == 130, err  # stopped by SIGINT (128 + 2)


def _replace_atomically(model: Path, data: bytes) -> None:
    """The model file replaced as the exporter replaces it: written beside, then renamed."""
    tmp = model.with_name("incoming.onnx")
    tmp.write_bytes(data)
    os.replace(tmp, model)


def test_swap_mid_stream_and_a_corrupt_file(domain, tmp_path):
    """Model 1 serves, the file is replaced by model 2 (atomically) mid-stream, then by a
    corrupt file: every pose comes back exactly once, from model 1 until some pose and from
    model 2 after it, bit for bit; the corrupt file is refused and model 2 keeps serving."""
    model = tmp_path / "model.onnx"
    shutil.copy(FIRST, model)
    cell = Cell(model, domain)

    try:
        x = _poses(3000, seed=2)
        cell.publish(x, first=0, rate_hz=1000.0,
                     at_index={1000: lambda: _replace_atomically(model, SECOND.read_bytes()),
                               2000: lambda: _replace_atomically(model, b"\x08\x07 half a model")})
        cell.wait(lambda: len(cell.got) == len(x), 30, "not every pose came back")
        got = cell.outputs(0, len(x))
        by_first, by_second = _shim(FIRST, x), _shim(SECOND, x)
        from_first = np.all(got == by_first, axis=1)
        from_second = np.all(got == by_second, axis=1)
        assert np.all(from_first | from_second), "an output from neither model"
        switch = int(np.argmax(from_second & ~from_first))
        # The node takes the new model between two messages it handles; a node behind the
        # stream still works on earlier poses when the file changes, so the switch may come
        # before pose 1000 in publication order, but once, and for good.
        assert 0 < switch < len(x) and np.all(from_second[switch:]) and np.all(from_first[:switch])
        # Diagnostics are published on a timer: one sent before the last poses were counted
        # is not the state to judge, so wait for a message that has counted every pose.
        cell.wait(lambda: cell.diagnostics and cell.diagnostics[-1]["poses_out"] == str(len(x))
                  and "model.onnx" in cell.diagnostics[-1]["last_load_error"], 20,
                  "no diagnostics with every pose counted and the corrupt file reported")
        d = cell.diagnostics[-1]
        assert d["generation"] == "2" and d["swaps"] == "1"
        assert d["poses_per_generation"] == f"1:{switch},2:{len(x) - switch}"
        print(f"swap after pose {switch}; corrupt file: {d['last_load_error']}")
    finally:
        code, out, err = cell.stop()
    assert code == 130, err  # stopped by SIGINT (128 + 2)
    assert "loaded" in err and "kept" in err


def _until(condition, seconds: float, what: str) -> None:
    end = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > end:
            pytest.fail(what)
        time.sleep(0.01)


def _watched(monkeypatch, model: Path, settle: float):
    """A ModelWatcher on `model` (no ROS), what it delivers and reports, and two counters:
    the loads that failed and the polls."""
    from posecorr.ros2 import node

    failed, polls = [], []
    load, key = node.load_checked, node._file_key

    def load_checked(path, allow=None):
        try:
            return load(path, allow)
        except Exception as exc:
            failed.append(exc)
            raise

    def file_key(path):
        polls.append(path)
        return key(path)

    monkeypatch.setattr(node, "load_checked", load_checked)
    monkeypatch.setattr(node, "_file_key", file_key)
    delivered, reported = [], []
    watcher = node.ModelWatcher(model, delivered.append, reported.append, settle=settle)
    watcher.start()
    return watcher, delivered, reported, failed, polls


def test_a_model_file_written_with_a_pause_is_not_reported_half_written(tmp_path, monkeypatch):
    """A slow copy in place: half the file, a pause in which the watcher reads the half and
    fails, then the rest. The half was reported as a load error (the old model serving on);
    now nothing is reported and the whole file is delivered. The settle time is beyond the
    test's length, so no pause of a loaded machine reaches it."""
    from posecorr.ros2.node import model_id

    model = tmp_path / "model.onnx"
    shutil.copy(FIRST, model)
    watcher, delivered, reported, failed, _ = _watched(monkeypatch, model, settle=3600.0)
    try:
        data = SECOND.read_bytes()
        with open(model, "wb") as f:
            f.write(data[:len(data) // 2])
            f.flush()
            _until(lambda: failed, 30, "the half-written file was never read")
            f.write(data[len(data) // 2:])
        _until(lambda: delivered, 30, "the completed file was never delivered")
    finally:
        watcher.stop()
        watcher.join(10)
    assert reported == [] and [d.model_id for d in delivered] == [model_id(model, data)]


def test_a_bad_model_file_at_rest_is_reported_once_settled(tmp_path, monkeypatch):
    """A file that fails and stays as it is: reported once it has not changed for the settle
    time (not before), and once only, however many polls follow."""
    model = tmp_path / "model.onnx"
    shutil.copy(FIRST, model)
    watcher, delivered, reported, failed, polls = _watched(monkeypatch, model, settle=0.5)
    try:
        _replace_atomically(model, b"\x08\x07 half a model")
        written = time.monotonic()
        _until(lambda: reported, 30, "the bad file was never reported")
        assert time.monotonic() - written >= 0.5 and len(failed) == 1
        seen = len(polls)
        _until(lambda: len(polls) >= seen + 20, 30, "the watcher stopped polling")
    finally:
        watcher.stop()
        watcher.join(10)
    assert len(reported) == 1 and reported[0].startswith(f"{model}: ") and not delivered, reported


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signals_end_the_node_cleanly(domain, tmp_path, sig):
    cell = Cell(FIRST, domain)
    cell.publish(_poses(20, seed=3), first=0, rate_hz=500.0)
    cell.wait(lambda: len(cell.got) == 20, 10, "poses lost")
    code, out, err = cell.stop(sig)
    # the conventional 128 + signal number, as every verb (README: SIGTERM 143, Ctrl-C 130)
    assert code == {signal.SIGINT: 130, signal.SIGTERM: 143}[sig] and "Traceback" not in err, err
    assert out.startswith("stopped: 20 poses in, 20 out, 0 refused"), out


def test_without_the_extra_one_line_names_it(tmp_path):
    """A Python without rclpy: the CLI names the extra, exit 2 (simulated by hiding rclpy)."""
    hide = tmp_path / "hide"
    hide.mkdir()
    (hide / "rclpy.py").write_text("raise ModuleNotFoundError(\"No module named 'rclpy'\", name='rclpy')\n")
    env = {**os.environ, "PYTHONPATH": f"{hide}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    r = subprocess.run([POSECORR, "ros2", str(FIRST)], capture_output=True, text=True, env=env,
                       timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "posecorr[ros2]" in r.stderr, r.stderr


def test_model_parameter_switches_the_served_file(domain, tmp_path):
    """`ros2 param set /posecorr model OTHER.onnx`, done through rclpy's parameter client
    (the service `ros2 param` calls): the node serves the other file from then on."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    cell = Cell(FIRST, domain)
    try:
        client = AsyncParameterClient(cell.node, "posecorr")
        assert client.wait_for_services(timeout_sec=10.0)
        future = client.set_parameters([Parameter("model", value=str(SECOND))])
        cell.wait(future.done, 10, "the parameter service did not answer")
        assert all(r.successful for r in future.result().results)
        cell.wait(lambda: cell.diagnostics[-1]["pending_model"].startswith(SECOND.name), 10,
                  "the node did not load the file the parameter names")
        x = _poses(50, seed=5)
        cell.publish(x, first=0, rate_hz=500.0)
        cell.wait(lambda: len(cell.got) == len(x), 10, "not every pose came back")
        np.testing.assert_array_equal(cell.outputs(0, len(x)), _shim(SECOND, x))
        cell.wait(lambda: cell.diagnostics[-1]["model"].startswith(SECOND.name), 5, "diagnostics lag")
    finally:
        code, out, err = cell.stop()
    assert code == 130, err  # stopped by SIGINT (128 + 2)


def test_input_frame_refuses_poses_in_another_frame(domain, tmp_path):
    """--input-frame tracker: poses in 'lighthouse' are refused and counted, one log line for
    the frame however many poses; the poses in 'tracker' around them are corrected, labelled
    in the robot's frame."""
    cell = Cell(FIRST, domain, "--input-frame", "tracker")
    try:
        x = _poses(60, seed=6)
        cell.publish(x[:20], first=0, rate_hz=500.0)
        cell.publish(x[20:50], first=20, rate_hz=500.0, frame="lighthouse")
        cell.publish(x[50:], first=50, rate_hz=500.0)
        cell.wait(lambda: cell.diagnostics[-1]["poses_in"] == "60", 10, "poses lost")
        d = cell.diagnostics[-1]
        assert (d["poses_out"], d["refused"]) == ("30", "30")
        assert "frame 'lighthouse'" in d["last_refusal"] and "'tracker'" in d["last_refusal"], d
        assert sorted(cell.got) == [k * 1_000_000 for k in [*range(20), *range(50, 60)]]
        np.testing.assert_array_equal(cell.outputs(50, 10), _shim(FIRST, x[50:]))
    finally:
        code, out, err = cell.stop()
    assert code == 130, err
    assert "input frame 'tracker', output frame base_link" in err, err
    assert [line for line in err.splitlines() if "frame 'lighthouse'" in line] == [
        "posecorr ros2: refusing poses in frame 'lighthouse': the model takes 'tracker' (--input-frame)"], err


def test_without_input_frame_every_frame_is_taken_and_named_once(domain):
    """No --input-frame: poses in any frame are corrected, and the log names each distinct
    frame once, so a tracker publishing in an unexpected frame is seen."""
    cell = Cell(FIRST, domain)
    try:
        x = _poses(30, seed=7)
        cell.publish(x[:20], first=0, rate_hz=500.0, frame="lighthouse")
        cell.publish(x[20:], first=20, rate_hz=500.0)
        cell.wait(lambda: len(cell.got) == len(x), 10, "poses lost")
        np.testing.assert_array_equal(cell.outputs(0, len(x)), _shim(FIRST, x))
    finally:
        code, out, err = cell.stop()
    assert code == 130, err
    named = [line for line in err.splitlines() if "taken unchecked" in line]
    assert len(named) == 2 and "'lighthouse'" in named[0] and "'tracker'" in named[1], err
    assert "input frame any, output frame base_link" in err, err


def test_model_parameter_naming_a_file_that_cannot_serve_is_refused(domain, tmp_path):
    """`model` set to a missing file, then to a corrupt one: each set is refused with the
    reason, the parameter still names the served file, the reason is logged once and in the
    diagnostics, and the served file is still watched (replacing it swaps the model)."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    from posecorr.ros2.node import model_id

    model = tmp_path / "model.onnx"
    shutil.copy(FIRST, model)
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"\x08\x07 half a model")
    cell = Cell(model, domain)
    try:
        client = AsyncParameterClient(cell.node, "posecorr")
        assert client.wait_for_services(timeout_sec=10.0)
        for target, why in [(tmp_path / "missing.onnx", "No such file or directory"),
                            (corrupt, "truncated file")]:
            future = client.set_parameters([Parameter("model", value=str(target))])
            cell.wait(future.done, 10, "the parameter service did not answer")
            (result,) = future.result().results
            assert not result.successful and str(target) in result.reason and why in result.reason, result
            future = client.get_parameters(["model"])
            cell.wait(future.done, 10, "the parameter service did not answer")
            assert future.result().values[0].string_value == str(model)
            cell.wait(lambda: str(target) in cell.diagnostics[-1]["last_load_error"], 5,
                      "the refusal is not in the diagnostics")
        tmp = tmp_path / "incoming.onnx"
        shutil.copy(SECOND, tmp)
        os.replace(tmp, model)
        cell.wait(lambda: cell.diagnostics[-1]["pending_model"] == model_id(model, SECOND.read_bytes()),
                  10, "the served file is no longer watched")
    finally:
        code, out, err = cell.stop()
    assert code == 130, err
    refused = [line for line in err.splitlines() if "model parameter refused" in line]
    assert len(refused) == 2 and "missing.onnx" in refused[0] and "corrupt.onnx" in refused[1], err


def test_a_failed_file_after_a_swap_not_yet_taken_names_the_model_that_will_serve(domain, tmp_path):
    """Model 2 loaded but not taken (no pose came since), then a corrupt file: the log says
    model 2 is kept, the one the next pose gets, not model 1."""
    from posecorr.ros2.node import model_id

    model = tmp_path / "model.onnx"
    shutil.copy(FIRST, model)
    cell = Cell(model, domain)

    second = model_id(model, SECOND.read_bytes())
    try:
        _replace_atomically(model, SECOND.read_bytes())
        cell.wait(lambda: cell.diagnostics[-1]["pending_model"] == second, 10, "model 2 not loaded")
        _replace_atomically(model, b"\x08\x07 half a model")
        cell.wait(lambda: cell.diagnostics[-1]["last_load_error"], 10, "the corrupt file not reported")
        assert cell.diagnostics[-1]["pending_model"] == second
    finally:
        code, out, err = cell.stop()
    assert code == 130, err
    (kept,) = [line for line in err.splitlines() if " kept " in line]
    assert kept.startswith(f"posecorr ros2: kept {second}: "), err


def test_a_slow_copy_over_the_model_file_swaps_without_a_load_error(domain, tmp_path):
    """The model file written in place with a pause of 0.5 s mid-file (five times the 0.1 s
    after which the watcher reads it, a quarter of the 2 s it waits before saying a file
    fails): the node logged a false load error for the half; now it logs none, and the
    completed file serves."""
    from posecorr.ros2.node import model_id

    model = tmp_path / "model.onnx"
    shutil.copy(FIRST, model)
    cell = Cell(model, domain)
    data = SECOND.read_bytes()
    try:
        with open(model, "wb") as f:
            f.write(data[:len(data) // 2])
            f.flush()
            cell.spin(0.5)
            f.write(data[len(data) // 2:])
        cell.wait(lambda: cell.diagnostics[-1]["pending_model"] == model_id(model, data), 10,
                  "the completed file was not loaded")
        x = _poses(20, seed=11)
        cell.publish(x, first=0, rate_hz=500.0)
        cell.wait(lambda: len(cell.got) == len(x), 10, "poses lost")
        np.testing.assert_array_equal(cell.outputs(0, len(x)), _shim(SECOND, x))
        assert all(d["last_load_error"] == "" for d in cell.diagnostics)
    finally:
        code, out, err = cell.stop()
    assert code == 130, err
    assert " kept " not in err and "generation 2" in err, err


def test_non_unit_quaternions_are_refused(domain):
    """A quaternion whose norm is off 1 by more than 1e-3 is refused and counted; one within
    it is corrected."""
    cell = Cell(FIRST, domain)
    try:
        x = _poses(2, seed=8)
        x[0, 3:] *= 1.0005
        x[1, 3:] *= 1.01
        cell.publish(x, first=0, rate_hz=500.0)
        cell.wait(lambda: cell.diagnostics[-1]["poses_in"] == "2", 10, "poses lost")
        d = cell.diagnostics[-1]
        assert (d["poses_out"], d["refused"]) == ("1", "1") and list(cell.got) == [0]
        assert "norm 1.010000" in d["last_refusal"] and "within 0.001 of 1" in d["last_refusal"], d
        nan = _poses(1, seed=9)
        nan[0, 1] = np.nan   # the runtime's words name the column: the node's said "a value is not finite"
        cell.publish(nan, first=2, rate_hz=500.0)
        cell.wait(lambda: cell.diagnostics[-1]["poses_in"] == "3", 10, "the pose was lost")
        assert cell.diagnostics[-1]["last_refusal"] == ("stamp 0.002000000: non-finite input: pose 0: y is not finite "
                                                        "(expected a finite number)"), cell.diagnostics[-1]
    finally:
        code, out, err = cell.stop()
    # refusals were only in /diagnostics: a swap to a model that refuses every pose was silent
    said = [line for line in err.splitlines() if "refused so far" in line]
    assert len(said) == 1 and said[0].startswith("posecorr ros2: 1 pose refused so far; the last: stamp 0.001000000: "
                                                 "quaternion not unit: "), err


def test_a_bad_topic_name_is_a_usage_error():
    """It was 'internal error: InvalidTopicNameException: MODEL: ...', blaming the model."""
    bad = subprocess.run([POSECORR, "ros2", str(FIRST), "--input", "/bad//topic"], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1, bad.stderr
    assert "posecorr ros2: error: --input '/bad//topic': Invalid topic name: " in bad.stderr, bad.stderr


def test_two_nodes_named_apart_serve_one_domain(domain):
    """Two trackers on one ROS domain: with --node-name each node carries its own name (its
    parameters at /NAME, its diagnostics named so) and corrects its own topic with its own
    model; the node's name was fixed, so a second tracker needed a domain of its own."""
    from rclpy.parameter_client import AsyncParameterClient

    cell = Cell(FIRST, domain, "--node-name", "posecorr_left")
    right = subprocess.Popen([POSECORR, "ros2", str(SECOND), "--reliable", "--registration", "none",
                              "--node-name", "posecorr_right", "--input", "/right/pose",
                              "--output", "/right/pose_corrected"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=cell.env)
    try:
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_ALL)
        got_right: dict[int, PoseStamped] = {}
        cell.node.create_subscription(PoseStamped, "/right/pose_corrected",
                                      lambda m: got_right.__setitem__(Cell.key(m), m), qos)
        statuses: set[str] = set()
        cell.node.create_subscription(DiagnosticArray, "/diagnostics",
                                      lambda m: statuses.update(s.name for s in m.status), 10)
        left_pub, right_pub = cell.pub, cell.node.create_publisher(PoseStamped, "/right/pose", qos)
        cell.wait(lambda: right_pub.get_subscription_count() > 0
                  and {"posecorr_left", "posecorr_right"} <= set(cell.node.get_node_names()),
                  30, "the second node never came up")
        x = _poses(40, seed=10)
        cell.publish(x[:20], first=0, rate_hz=500.0)
        cell.pub = right_pub
        cell.publish(x[20:], first=20, rate_hz=500.0)
        cell.pub = left_pub
        cell.wait(lambda: len(cell.got) == 20 and len(got_right) == 20, 10, "poses lost")
        np.testing.assert_array_equal(cell.outputs(0, 20), _shim(FIRST, x[:20]))
        np.testing.assert_array_equal(
            [[m.pose.position.x, m.pose.position.y, m.pose.position.z, m.pose.orientation.w,
              m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z]
             for m in (got_right[(20 + k) * 1_000_000] for k in range(20))], _shim(SECOND, x[20:]))
        for name, model in (("posecorr_left", FIRST), ("posecorr_right", SECOND)):
            client = AsyncParameterClient(cell.node, name)
            assert client.wait_for_services(timeout_sec=10.0), name
            future = client.get_parameters(["model"])
            cell.wait(future.done, 10, f"/{name}'s parameter service did not answer")
            assert future.result().values[0].string_value == str(model)
        cell.wait(lambda: {"posecorr_left: pose correction", "posecorr_right: pose correction"} <= statuses,
                  10, "the diagnostics do not name both nodes")
    finally:
        code, out, err = cell.stop()
        if right.poll() is None:
            right.send_signal(signal.SIGINT)
        right_out, right_err = right.communicate(timeout=30)
    assert code == 130 and right.returncode == 130, (err, right_err)
    assert out.startswith("stopped: 20 poses in, 20 out") and right_out.startswith("stopped: 20 poses in, 20 out")


def test_a_bad_node_name_is_a_usage_error():
    """A name ROS refuses is said in one line naming --node-name, before ROS starts."""
    bad = subprocess.run([POSECORR, "ros2", str(FIRST), "--node-name", "left-1"], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1, bad.stderr
    assert bad.stderr.startswith("posecorr ros2: error: --node-name 'left-1': Invalid node name: "), bad.stderr


def test_a_swap_to_a_model_that_asks_other_poses_is_said(tmp_path):
    """A swapped-in model with a smaller box was loaded with 'loaded ... as generation 4' and
    nothing else, then refused 985 poses in a row."""
    import onnx

    from posecorr.ros2.node import contract_change

    sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))
    import graphs

    model = onnx.load(str(SECOND))
    for entry in model.metadata_props:
        if entry.key == "input_bounds":
            lo, hi = np.array(eval(entry.value))   # the exporter writes a JSON list of lists
            entry.value = str([lo.tolist(), (lo + 0.5 * (hi - lo)).tolist()])
    smaller = Corrector(graphs.signed(model))
    assert contract_change(Corrector(FIRST), Corrector(SECOND)) == ""
    said = contract_change(Corrector(SECOND), smaller)
    assert said.startswith("; unlike the served model, its box (input_bounds, m) [") and said.endswith(
        "leaves out part of the served model's: poses there will be refused"), said
    assert contract_change(smaller, Corrector(SECOND)) == ""


def test_a_refused_first_pose_does_not_set_the_time_origin(domain, tmp_path):
    """t0 was the first pose's stamp even when that pose was refused: a NaN at start-up
    stamped 0 made t = stamp - 0 for every later pose, and a time model refused them all."""
    from posecorr.simulate import simulate_session
    from posecorr.train.physics import PhysicsModel

    table = simulate_session(3, n=30, robot="ur5e", duration=600.0, extra={"drift": [0.002, -0.001, 0.001, 300.0]}).table
    t = table.time()
    model = tmp_path / "drift.onnx"
    PhysicsModel(("station", "mount", "drift")).fit(table.measured, table.reference, t=t).to_onnx(
        model, measured=table.measured, reference=table.reference, t=t)
    x = table.measured[:10].copy()
    x[0, 0] = np.nan
    cell = Cell(model, domain)
    try:
        cell.publish(x[:1], first=0, rate_hz=200.0)      # a start-up glitch, stamped 0
        cell.publish(x[1:], first=1_700_000_000_000, rate_hz=200.0)   # ms: stamps of today's clock
        cell.wait(lambda: cell.diagnostics and cell.diagnostics[-1]["poses_in"] == "10", 10, "poses lost")
        d = cell.diagnostics[-1]
        assert (d["poses_out"], d["refused"]) == ("9", "1"), d
    finally:
        cell.stop()


# rclpy's own report of the mismatched QoS calls a logger method it deprecated
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_the_summary_of_a_node_that_published_no_pose_says_so(domain):
    """A best-effort publisher and the node's reliable subscription never match: no pose
    comes in, and the summary says 'no poses' where the latency would be (it said nan)."""
    cell = Cell(FIRST, domain)
    try:
        cell.pub = cell.node.create_publisher(PoseStamped, "/tracker/pose", qos_profile_sensor_data)
        cell.publish(_poses(20, seed=9), first=0, rate_hz=500.0)
        cell.spin(0.5)
        assert cell.diagnostics[-1]["poses_in"] == "0" and not cell.got
    finally:
        code, out, err = cell.stop()
    assert code == 130, err
    assert out.startswith("stopped: 0 poses in, 0 out, 0 refused; per model generation 1:0; "
                          "added latency no poses"), out
    assert "nan" not in out, out


def test_registration_maps_each_pose_as_ingest_mapped_the_table(domain):
    """--registration x,y,z,qw,qx,qy,qz: a pose published in the tracker's frame is mapped by
    it before the model, as `ingest --registration` mapped the table's measured poses (scipy's
    Rotation, the independent truth, makes the raw poses from poses in the model's box); a
    registration that is no transform is refused in one line before ROS starts."""
    from scipy.spatial.transform import Rotation

    turn, shift = Rotation.from_euler("xyz", [0.2, -0.1, 0.7]), np.array([0.1, -0.2, 0.05])
    qx, qy, qz, qw = turn.as_quat()
    x = _poses(40, seed=9)
    raw_p = turn.inv().apply(x[:, :3] - shift)
    raw_q = (turn.inv() * Rotation.from_quat(x[:, [4, 5, 6, 3]])).as_quat()[:, [3, 0, 1, 2]]
    cell = Cell(FIRST, domain, "--registration", ",".join(repr(float(v)) for v in (*shift, qw, qx, qy, qz)))
    try:
        cell.publish(np.column_stack([raw_p, raw_q]), first=0, rate_hz=500.0)
        cell.wait(lambda: len(cell.got) == len(x), 10, "poses lost")
        np.testing.assert_allclose(cell.outputs(0, len(x)), _shim(FIRST, x), rtol=0, atol=2e-6)
        # a quaternion of norm 3 is refused as the runtime refuses it, not mapped into a rotation
        cell.publish(np.column_stack([raw_p[:1], 3 * raw_q[:1]]), first=len(x), rate_hz=500.0)
        cell.wait(lambda: cell.diagnostics[-1]["refused"] == "1", 10, "the pose was not refused")
        assert "quaternion not unit" in cell.diagnostics[-1]["last_refusal"], cell.diagnostics[-1]
        assert len(cell.got) == len(x)
    finally:
        code, out, err = cell.stop()
    assert code == 130, err
    assert "poses mapped by the registration first" in err, err
    bad = subprocess.run([POSECORR, "ros2", str(FIRST), "--registration", "1,2"], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1, bad.stderr
    assert "--registration '1,2': expected paper, none or x,y,z[,qw,qx,qy,qz]" in bad.stderr, bad.stderr


def test_the_nodes_registration_defaults_to_ingests():
    """A model fitted on a table ingested with the defaults takes the bridge's poses with the
    node's defaults: both map by the paper's base_T_station; none maps nothing."""
    from posecorr.cli import build_parser
    from posecorr.geometry import base_T_station
    from posecorr.ingest.pipeline import IngestOptions

    parse = build_parser().parse_args
    np.testing.assert_array_equal(parse(["ros2", str(FIRST)]).registration, IngestOptions().registration)
    np.testing.assert_array_equal(IngestOptions().registration, base_T_station())
    assert parse(["ros2", str(FIRST), "--registration", "none"]).registration is None


def test_poses_turned_beyond_the_training_orientations_are_counted(domain, tmp_path):
    """A model fitted at one orientation (Exp2's nine poses, `fit`'s default PMC) serves its
    own poses without a word; the same poses turned by 2 degrees are corrected all the same,
    counted in the diagnostics as `apply` counts them, and named in the summary."""
    from scipy.spatial.transform import Rotation

    from posecorr.cli import main
    from posecorr.data import read_table

    data, model = tmp_path / "exp2.csv", tmp_path / "pmc.onnx"
    data.write_bytes((ROOT / "tests" / "data" / "realdata" / "20200717_Exp2.csv").read_bytes())
    assert main(["fit", str(data), "--effects", "station,mount", "--method", "pmc", "-o", str(model)]) == 0
    own = read_table(data).measured
    turned = own.copy()
    turned[:, 3:] = (Rotation.from_quat(own[:, 3:], scalar_first=True)
                     * Rotation.from_euler("x", 2.0, degrees=True)).as_quat(scalar_first=True)
    cell = Cell(model, domain)
    try:
        cell.publish(own, first=0, rate_hz=500.0)
        cell.wait(lambda: cell.diagnostics[-1]["poses_out"] == "9", 10, "poses lost")
        assert cell.diagnostics[-1]["beyond_training_orientations"] == "0"
        cell.publish(turned, first=9, rate_hz=500.0)
        cell.wait(lambda: cell.diagnostics[-1]["poses_out"] == "18", 10, "poses lost")
        assert cell.diagnostics[-1]["beyond_training_orientations"] == "9"
        assert cell.diagnostics[-1]["refused"] == "0"
        np.testing.assert_allclose(cell.outputs(9, 9), _shim(model, turned), rtol=0, atol=2e-6)
    finally:
        code, out, err = cell.stop()
    assert code == 130, err
    assert out.startswith("stopped: 18 poses in, 18 out, 0 refused, 9 beyond the orientations the model was "
                          "fitted on; per model generation 1:18; "), out
