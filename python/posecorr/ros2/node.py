"""The correcting node: PoseStamped in, corrected PoseStamped out, models swapped live.

- Each incoming pose is corrected on the subscription's thread by the C runtime (the
  shim's single-pose path) and published with the input's stamp and the robot's frame id
  (`frame`): the model maps the measured pose into the frame its reference poses were in.
  A pose the model refuses (non-finite; a quaternion of norm off 1 by more than 1e-3, a
  zero one included; outside the model's `input_bounds`, or its `time_bounds`; a result
  that is not a pose) is not published; it is counted, and the last reason is in the
  diagnostics.
- The input's frame id: the model knows poses only in the frame it was fitted in, and the
  node cannot tell that frame from the file. With `input_frame` set, a pose in any other
  frame is refused (counted, one log line per distinct frame); without it every frame is
  taken, and each distinct one is logged once, so a stream in an unexpected frame shows.
- The registration: a model fitted on a table that `ingest` mapped into the robot's base
  frame (its `--registration`) takes poses mapped the same way; with `registration` (4x4
  base_T_<tracker frame>) each pose is mapped so before the model, as ingest mapped them.
- Models with time take `t` from the stamps: seconds since the first pose corrected, or
  since `t0`.
- A pose refused is counted; the 1st, 10th, 100th ... refusal is logged with its reason.
- Hot swap: a watcher thread polls the model file (size, modification time, inode; read once
  it stayed the same for two polls, 0.1 s: a writer that pauses longer mid-file has its half
  read and refused quietly, the old model serving on, and the whole file loaded once it is
  complete; posecorr's exporter replaces files atomically) and the `model` parameter (`ros2
  param set /posecorr model new.onnx`). A new model is loaded and checked (the runtime's own
  contract checks, then probe poses: each alone must give the batch plan's result), then
  handed over; the subscription takes it between two messages, so every output comes from
  exactly one model and no pose is lost or duplicated. A watched file that fails leaves the
  old model serving; once it has not changed for `SETTLE_SECONDS` (2 s) the reason is logged,
  once, and in the diagnostics (a file still being written is no load error). The watched file
  is loaded on the watcher's thread; the parameter's file before the set is answered, so that
  one that cannot serve is refused with its reason, and the parameter and the watch stay on
  the model that serves. A model that takes other poses of the stream than the served one (the
  time input, a box that leaves out part of the served one's) is loaded with a line saying so;
  a watched file that is deleted is said once, the loaded model serving on.
- Diagnostics: a `diagnostic_msgs/DiagnosticArray` on /diagnostics every `diag_period`
  seconds: model id and generation, poses in / out / refused, poses per generation, the
  node's added latency (arrival of the message to its publication, p50 / p99 / max, µs),
  the last refusal and the last load error, and the poses corrected though turned beyond
  the orientations the model was fitted on (`posecorr.coverage`; a warning: its core
  extrapolates there).
"""
from __future__ import annotations

import hashlib
import os
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from posecorr.controller.checks import INPUT_NORM2_RANGE, Limits
from posecorr.controller.runtime import Corrector, PoseCorrError
from posecorr.coverage import Beyond
from posecorr.rotations import matrix_to_quat, quat_to_matrix
from posecorr.textui import counted

POLL_SECONDS = 0.05
# A watched file that fails to load is reported once it has not changed for this long: a
# slow copy that pauses mid-file (a network share, a loaded disk) completes the file before,
# and its half is never reported; a bad file at rest is said this much later, the old model
# serving meanwhile.
SETTLE_SECONDS = 2.0
LATENCY_WINDOW = 10_000
PROBE_POSES = 16
# distinct input frames logged: a stream naming a new frame in every message must not log
# every message
FRAMES_LOGGED = 16


@dataclass
class Loaded:
    """A checked model and what the diagnostics say of it."""
    corrector: Corrector
    path: Path
    model_id: str
    generation: int = 0
    turned: Beyond | None = None   # the orientations it was fitted on, and the poses beyond


# The refusal counts the log names (`_Correcting._refused`).
_LOGGED_COUNTS = frozenset(10 ** k for k in range(19))


@dataclass
class Counters:
    poses_in: int = 0
    poses_out: int = 0
    refused: int = 0
    turned: int = 0
    per_generation: dict[int, int] = field(default_factory=dict)
    last_refusal: str = ""
    last_load_error: str = ""
    swaps: int = 0


def model_id(path: Path, data: bytes) -> str:
    """The file's name and the first 12 hex digits of its SHA-256: which bytes serve."""
    return f"{path.name}@{hashlib.sha256(data).hexdigest()[:12]}"


def _probe_poses(metadata: dict[str, str], n: int = PROBE_POSES) -> np.ndarray:
    """Poses inside the model's input_bounds (a 1 m box about the origin without them)."""
    import json

    rng = np.random.default_rng(20261125)
    lo, hi = np.full(3, -0.5), np.full(3, 0.5)
    try:
        box = np.asarray(json.loads(metadata["input_bounds"]), float)
        if box.shape == (2, 3) and np.all(box[0] <= box[1]):
            lo, hi = box
    except (KeyError, ValueError, TypeError):
        pass
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.hstack([rng.uniform(lo, hi, (n, 3)), q])


def load_checked(path: Path, allow: dict[str, bool] | None = None) -> Loaded:
    """Loads `path` with the C runtime and checks it: each probe pose alone must give the
    batch plan's result (bit for bit), and the results must be poses. allow: Corrector's
    allow_unbounded / allow_unsigned. Raises PoseCorrError (or OSError) with the reason."""
    from ..safeio import InputPathError, check_input

    try:  # a FIFO would block the read, and the parameter's is read on the executor's thread
        check_input(path)
    except InputPathError as exc:
        raise PoseCorrError(str(exc)) from None
    data = path.read_bytes()  # once: the bytes loaded are the bytes the id names
    try:
        corrector = Corrector(data, **(allow or {}))
    except PoseCorrError as exc:
        raise PoseCorrError(f"{path}: {str(exc).split(': ', 1)[-1]}", exc.status) from None
    probe = _probe_poses(corrector.metadata)
    # times inside the span the model was fitted on (time_bounds), where it answers
    span = Limits.from_metadata(corrector.metadata, corrector.takes_time, True).span or (0.0, 60.0)
    t = np.linspace(span[0], span[1], len(probe)) if corrector.takes_time else None
    batch = corrector.correct(probe, t)
    for i, pose in enumerate(probe):
        one = corrector.correct(pose, None if t is None else t[i])
        if not np.array_equal(one, batch[i]):
            raise PoseCorrError(f"{path}: probe pose {i} alone differs from the batch plan")
    return Loaded(corrector, path, model_id(path, data), turned=Beyond(corrector.metadata))


def contract_change(before: Corrector, after: Corrector) -> str:
    """'; unlike the served model, it takes the time t' and the like, where a swapped-in
    model asks other poses of the stream than the served one: the time input, or a box
    (input_bounds) that leaves out part of the served one's (poses there, corrected until
    now, will be refused); '' otherwise."""
    said = []
    if before.takes_time != after.takes_time:
        said.append("it takes the time t" if after.takes_time else "it takes no time t")
    old, new = (Limits.from_metadata(c.metadata, c.takes_time, True).box for c in (before, after))
    if np.any(new[0] > old[0]) or np.any(new[1] < old[1]):
        lo, hi = (", ".join(f"{v:.3f}" for v in end) for end in new)
        said.append(f"its box (input_bounds, m) [{lo}] to [{hi}] leaves out part of the served model's: poses "
                    "there will be refused")
    return f"; unlike the served model, {' and '.join(said)}" if said else ""


def load_error(path: Path, exc: Exception) -> str:
    """A failed load's reason in one line that names the file."""
    message = str(exc).splitlines()[0]
    return message if str(path) in message else f"{path}: {message}"


def _file_key(path: Path) -> tuple[int, int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns, st.st_ino


class ModelWatcher(threading.Thread):
    """Polls the model file and the requested path; hands checked models to `deliver`."""

    def __init__(self, path: Path, deliver, report_error, poll: float = POLL_SECONDS,
                 allow: dict[str, bool] | None = None, settle: float = SETTLE_SECONDS) -> None:
        super().__init__(name="posecorr-model-watcher", daemon=True)
        self._path = path
        self._allow = allow
        self._deliver, self._report_error = deliver, report_error
        self._poll, self._settle = poll, settle
        # not `_stop`: Thread.join calls a method of that name, which the Event hid
        self._halt = threading.Event()
        self._lock = threading.Lock()
        self._seen = _file_key(path)
        self._pending_key: tuple[int, int, int] | None = None
        self._stable = 0
        # a failed load is held in _failure, unsaid, until `settle` after _changed_at (monotonic)
        self._changed_at = 0.0
        self._failure = ""

    def switch(self, path: Path) -> str | None:
        """Serve `path` from now on (the `model` parameter): loaded and checked on the
        caller's thread, so that a file that cannot serve is refused and the watch stays
        where it was. Returns the reason, or None once the model is handed over."""
        key = _file_key(path)  # before the read: a change after it is loaded again by the watch
        try:
            loaded = load_checked(path, self._allow)
        except (PoseCorrError, OSError, ValueError) as exc:
            return load_error(path, exc)
        with self._lock:
            self._path, self._seen = path, key
            self._pending_key, self._stable, self._failure = None, 0, ""
            self._deliver(loaded)
        return None

    def stop(self) -> None:
        self._halt.set()

    def _due(self, path: Path) -> bool:
        """Whether the file is to be read now: it changed, then stayed the same for two polls.
        A failure held back is said here once the file has not changed for `settle` seconds:
        a writer that pauses mid-file is not reported, a bad file at rest is, once. Called
        under the lock."""
        key = _file_key(path)
        if key is None and self._seen is not None:   # said once, until it is back
            self._seen = self._pending_key = None
            self._failure = ""
            self._report_error(f"{path}: the file is gone; the loaded model serves on, and a file "
                               "written there is loaded")
        if key is None:
            return False
        if key == self._seen:
            if self._failure and time.monotonic() - self._changed_at >= self._settle:
                self._report_error(self._failure)
                self._failure = ""
            return False
        if key != self._pending_key:  # changed since the last poll: the bytes that failed are gone
            self._pending_key, self._stable, self._failure = key, 0, ""
            self._changed_at = time.monotonic()
            return False
        self._stable += 1
        if self._stable < 2:
            return False
        self._seen = key
        return True

    def run(self) -> None:
        while not self._halt.wait(self._poll):
            with self._lock:
                path = self._path
                if not self._due(path):
                    continue
            loaded, reason = None, ""
            try:
                loaded = load_checked(path, self._allow)
            except (PoseCorrError, OSError, ValueError) as exc:
                reason = load_error(path, exc)
            with self._lock:
                if path != self._path:  # the parameter moved the watch while this file loaded
                    continue
                if loaded is None:
                    self._failure = reason   # perhaps a writer paused mid-file: said once the file settles
                else:
                    self._deliver(loaded)


def _import_ros() -> dict[str, Any]:
    """rclpy and the messages, imported on demand (the `ros2` extra)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseStamped
    from rcl_interfaces.msg import SetParametersResult
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    return dict(rclpy=rclpy, Node=Node, PoseStamped=PoseStamped, DiagnosticArray=DiagnosticArray,
                DiagnosticStatus=DiagnosticStatus, KeyValue=KeyValue,
                SetParametersResult=SetParametersResult, QoSProfile=QoSProfile,
                ReliabilityPolicy=ReliabilityPolicy, HistoryPolicy=HistoryPolicy,
                qos_profile_sensor_data=qos_profile_sensor_data)


def _percentile(values: deque, q: float) -> float:
    return float(np.percentile(np.fromiter(values, float), q)) if values else float("nan")


class _Correcting:
    """The node's state and callbacks; make_node mixes it into rclpy's Node, which is
    imported only with the `ros2` extra."""

    def __init__(self, ros: dict[str, Any], first: Loaded, model: Path, *, node_name: str,
                 input_topic: str, output_topic: str, frame: str, input_frame: str | None,
                 registration: np.ndarray | None, reliable: bool, t0: float | None, diag_period: float,
                 log) -> None:
        super().__init__(node_name)
        self._ros, self._log = ros, log
        self.watcher: ModelWatcher | None = None
        self.current = first
        self.incoming: Loaded | None = None
        self.counts = Counters(per_generation={1: 0})
        self.latency_us: deque = deque(maxlen=LATENCY_WINDOW)
        self.t0 = t0
        self.frame = frame
        self.input_frame = input_frame
        self.registration = registration
        self.frames_seen: set[str] = set()
        # the frame of the last pose taken: only a pose in another one is looked at (one
        # string compare on the hot path); None lets the first pose's frame be logged
        self._frame_taken = input_frame
        self._generation = 1
        self._handover = threading.Lock()
        self._create_topics(input_topic, output_topic, reliable)
        self.declare_parameter("model", str(model))
        self.add_on_set_parameters_callback(self.on_parameters)
        self.timer = self.create_timer(diag_period, self.publish_diagnostics)
        self._out = ros["PoseStamped"]()
        self._out.header.frame_id = frame

    def _create_topics(self, input_topic: str, output_topic: str, reliable: bool) -> None:
        ros = self._ros
        if reliable:
            # Keep all: a burst waits in the queues (the writer is held back) instead of
            # overwriting poses the node has not corrected yet.
            qos = ros["QoSProfile"](depth=1000, reliability=ros["ReliabilityPolicy"].RELIABLE,
                                    history=ros["HistoryPolicy"].KEEP_ALL)
        else:
            qos = ros["qos_profile_sensor_data"]
        self.publisher = self.create_publisher(ros["PoseStamped"], output_topic, qos)
        self.diagnostics = self.create_publisher(ros["DiagnosticArray"], "/diagnostics", 10)
        self.subscription = self.create_subscription(ros["PoseStamped"], input_topic,
                                                     self.on_pose, qos)

    # -- hot path ----------------------------------------------------------------------
    def _take_incoming(self) -> Loaded:
        """The model for this pose: a delivered one is taken between two messages, so
        every output comes from exactly one model."""
        with self._handover:
            if self.incoming is not None:
                self.current, self.incoming = self.incoming, None
                self.counts.per_generation.setdefault(self.current.generation, 0)
                self.counts.swaps += 1
        return self.current

    def on_pose(self, msg) -> None:
        arrival = time.perf_counter()
        loaded = self._take_incoming()
        self.counts.poses_in += 1
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        if msg.header.frame_id != self._frame_taken and not self._take_frame(msg.header.frame_id, stamp):
            return
        p, o = msg.pose.position, msg.pose.orientation
        pose = np.array([p.x, p.y, p.z, o.w, o.x, o.y, o.z])
        # t0 is the first corrected pose's stamp: a refused first pose (a NaN at start-up) set
        # it once to a stamp of 0, and a time model refused every pose after it
        t0 = stamp if self.t0 is None else self.t0
        try:   # a pose that is not one (nan, a zero quaternion) is refused by the runtime, in its words
            if self.registration is not None:
                pose = self._registered(pose)
            c = loaded.corrector.correct(pose, stamp - t0)
        except PoseCorrError as exc:
            self._refused(f"stamp {stamp:.9f}: {str(exc).splitlines()[0]}")
            return
        self.t0 = t0
        self._publish_pose(msg.header.stamp, c)
        if loaded.turned is not None and loaded.turned.one(pose[3:].tolist()):   # floats: 0.4 us, not 1.3
            self.counts.turned += 1
        self.counts.poses_out += 1
        self.counts.per_generation[loaded.generation] += 1
        self.latency_us.append((time.perf_counter() - arrival) * 1e6)

    def _refused(self, why: str, logged: bool = True) -> None:
        """Counted; logged at the 1st, 10th, 100th ... refusal: a model that refuses every pose
        (a swap to another box, the registration of another frame) is said in the log, not
        only in /diagnostics, and a stream of refusals is a few lines. A pose of a refused
        frame is not `logged`: its frame is, once."""
        self.counts.refused += 1
        self.counts.last_refusal = why
        if logged and self.counts.refused in _LOGGED_COUNTS:
            self._log(f"posecorr ros2: {counted(self.counts.refused, 'pose')} refused so far; the last: {why}")

    def _registered(self, pose: np.ndarray) -> np.ndarray:
        """The pose mapped by the registration, as ingest mapped the table's measured poses. A
        quaternion that is not unit is left as it is, for the runtime to refuse in its words:
        mapped, a norm-3 one would come out unit, a made-up rotation."""
        if not INPUT_NORM2_RANGE[0] <= float(pose[3:] @ pose[3:]) <= INPUT_NORM2_RANGE[1]:
            return pose
        T = self.registration
        return np.concatenate([T[:3, :3] @ pose[:3] + T[:3, 3], matrix_to_quat(T[:3, :3] @ quat_to_matrix(pose[3:]))])

    def _take_frame(self, frame: str, stamp: float) -> bool:
        """Whether a pose in `frame`, another than the last pose's, is corrected: any frame
        without input_frame, only that one with it. Each distinct frame is logged once."""
        first_time = frame not in self.frames_seen and len(self.frames_seen) < FRAMES_LOGGED
        if first_time:
            self.frames_seen.add(frame)
        if self.input_frame is None:
            self._frame_taken = frame
            if first_time:
                self._log(f"posecorr ros2: input in frame {frame!r}, taken unchecked (--input-frame "
                          f"names the frame the model was fitted in and refuses any other)")
            return True
        self._refused(f"stamp {stamp:.9f}: frame {frame!r}, the model takes {self.input_frame!r} (--input-frame)",
                      logged=False)
        if first_time:
            self._log(f"posecorr ros2: refusing poses in frame {frame!r}: the model takes "
                      f"{self.input_frame!r} (--input-frame)")
        return False

    def _publish_pose(self, stamp, c: np.ndarray) -> None:
        out = self._out  # reused: no message allocated per pose
        out.header.stamp = stamp
        out.pose.position.x, out.pose.position.y, out.pose.position.z = (
            float(c[0]), float(c[1]), float(c[2]))
        (out.pose.orientation.w, out.pose.orientation.x, out.pose.orientation.y,
         out.pose.orientation.z) = float(c[3]), float(c[4]), float(c[5]), float(c[6])
        self.publisher.publish(out)

    # -- off the hot path (the watcher's thread and the timer) --------------------------
    def deliver(self, loaded: Loaded) -> None:
        with self._handover:
            serving = self.incoming or self.current
            self._generation += 1
            loaded.generation = self._generation
            self.incoming = loaded
        self.counts.last_load_error = ""
        self._log(f"posecorr ros2: loaded {loaded.model_id} as generation {loaded.generation}"
                  + contract_change(serving.corrector, loaded.corrector))

    def report_error(self, message: str) -> None:
        with self._handover:  # a model loaded but not taken yet serves from the next pose on
            serving = self.incoming or self.current
        self.counts.last_load_error = message
        self._log(f"posecorr ros2: kept {serving.model_id}: {message}")

    def on_parameters(self, params):
        """A `model` that cannot be loaded and checked is refused with the reason (the
        parameter keeps naming the served model). The load runs here, on the executor's
        thread, before the set is answered: 0.7-3.3 ms for the shipped models, during which
        poses wait in the queue."""
        for p in params:
            if p.name == "model":
                reason = self.watcher.switch(Path(str(p.value)))
                if reason is not None:
                    self.report_error(f"model parameter refused: {reason}")
                    return self._ros["SetParametersResult"](successful=False, reason=reason)
        return self._ros["SetParametersResult"](successful=True)

    def diagnostic_values(self) -> dict[str, str]:
        c = self.counts
        lat = self.latency_us
        incoming = self.incoming
        return {
            "model": self.current.model_id, "generation": str(self.current.generation),
            # loaded and checked, taken with the next pose
            "pending_model": incoming.model_id if incoming is not None else "",
            "poses_in": str(c.poses_in), "poses_out": str(c.poses_out),
            "refused": str(c.refused), "beyond_training_orientations": str(c.turned), "swaps": str(c.swaps),
            "poses_per_generation": ",".join(f"{g}:{n}" for g, n in sorted(c.per_generation.items())),
            "latency_p50_us": f"{_percentile(lat, 50):.1f}",
            "latency_p99_us": f"{_percentile(lat, 99):.1f}",
            "latency_max_us": f"{max(lat) if lat else float('nan'):.1f}",
            "last_refusal": c.last_refusal, "last_load_error": c.last_load_error,
        }

    def publish_diagnostics(self) -> None:
        ros = self._ros
        status = ros["DiagnosticStatus"]()
        status.name = f"{self.get_name()}: pose correction"
        status.hardware_id = self.current.model_id
        c = self.counts
        status.level = ros["DiagnosticStatus"].WARN if (c.refused or c.last_load_error or c.turned) \
            else ros["DiagnosticStatus"].OK
        said = [f"{counted(n, 'pose')} {what}" for n, what in ((c.refused, "refused"),
                                                              (c.turned, "beyond the training orientations")) if n]
        status.message = c.last_load_error or "; ".join(said) or "ok"
        status.values = [ros["KeyValue"](key=k, value=v) for k, v in self.diagnostic_values().items()]
        array = ros["DiagnosticArray"]()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self.diagnostics.publish(array)


def make_node(model: Path, *, input_topic: str = "/tracker/pose",
              output_topic: str = "/tracker/pose_corrected", frame: str = "base_link",
              input_frame: str | None = None, registration: np.ndarray | None = None,
              reliable: bool = False, t0: float | None = None, diag_period: float = 1.0,
              node_name: str = "posecorr", log=print, allow: dict[str, bool] | None = None):
    """The node (rclpy must be initialised). Returns (node, watcher); the caller spins it
    and stops the watcher."""
    ros = _import_ros()
    first = load_checked(model, allow)
    first.generation = 1
    node_class = type("CorrectorNode", (_Correcting, ros["Node"]), {})
    node = node_class(ros, first, model, node_name=node_name, input_topic=input_topic,
                      output_topic=output_topic, frame=frame, input_frame=input_frame,
                      registration=registration, reliable=reliable, t0=t0, diag_period=diag_period, log=log)
    node.watcher = ModelWatcher(model, node.deliver, node.report_error, allow=allow)
    node.watcher.start()
    return node, node.watcher


def run_node(model: Path, log=print, **options) -> dict[str, str]:
    """`posecorr ros2`: spins until SIGINT or SIGTERM (KeyboardInterrupt here), then shuts
    down cleanly and returns the last diagnostics, with "stopped_by": the signal's name
    ("SIGINT", "SIGTERM") or "" when ROS shut down on its own."""
    ros = _import_ros()
    rclpy = ros["rclpy"]
    from rclpy.signals import SignalHandlerOptions

    # SIGINT and SIGTERM set a flag the spin loop reads between two spins (each at most 0.1 s):
    # raised as KeyboardInterrupt, one could land between a pose's publication and its count,
    # and the summary said one pose fewer out than were published. SIGINT is taken even where
    # the node was started in the background of a script (which starts it ignored); rclpy's
    # own handlers would end the context under the executor instead.
    import signal
    import threading

    stop = {"by": ""}
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        def _stop(signum: int, frame: Any) -> None:
            stop["by"] = "SIGTERM" if signum == signal.SIGTERM else "SIGINT"

        previous = {signum: signal.signal(signum, _stop) for signum in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = watcher = None
    try:
        node, watcher = make_node(model, log=log, **options)
        log(f"posecorr ros2: {node.current.model_id} on {node.subscription.topic_name} -> "
            f"{node.publisher.topic_name} (input frame "
            f"{'any' if node.input_frame is None else repr(node.input_frame)}, output frame {node.frame}"
            f"{'' if node.registration is None else ', poses mapped by the registration first'})")
        # rclpy's experimental events executor measured no faster here (1,020 against 1,140
        # poses/s unpaced, bench/ros2_latency.py, load 1.9)
        from rclpy.executors import SingleThreadedExecutor

        from ..safeio import Terminated

        executor = SingleThreadedExecutor()
        executor.add_node(node)
        try:
            while rclpy.ok() and not stop["by"]:
                executor.spin_once(timeout_sec=0.1)
        except KeyboardInterrupt as exc:   # off the main thread: the CLI's handlers raise
            stop["by"] = "SIGTERM" if isinstance(exc, Terminated) else "SIGINT"
        finally:
            executor.shutdown()
        return {**node.diagnostic_values(), "stopped_by": stop["by"]}
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if watcher is not None:
            watcher.stop()
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
