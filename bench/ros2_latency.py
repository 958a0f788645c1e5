"""`posecorr ros2` measured (part of `make bench`, bench/results/ros2.json).

The node runs as the CLI in its own process (reliable QoS, the shipped zhou MLP); this
script publishes PoseStamped at 250 Hz and at 1 kHz and, third, as fast as it can, and
listens to the corrected poses. Reported per run: poses sent and received, the node's added
latency as the node measures it (arrival of the message in its callback to its publication:
p50 / p99 / max, from its /diagnostics), the round trip seen here (publication of the pose
to arrival of its correction, through DDS both ways), and for the unpaced run the poses per
second the node sustained. Beside it, `posecorr-run` on the same poses through a pipe
(one line in, one line out, each read before the next is written): its round trip.
The load average is recorded before and after.

    .venv/bin/python bench/ros2_latency.py
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
RESULTS = ROOT / "bench" / "results" / "ros2.json"
BIN = Path(sys.executable).parent


def _stats(us: np.ndarray) -> dict[str, float]:
    return {"p50_us": round(float(np.percentile(us, 50)), 1),
            "p99_us": round(float(np.percentile(us, 99)), 1),
            "max_us": round(float(us.max()), 1)}


def _poses(n: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.hstack([rng.uniform(-0.4, 0.4, (n, 3)), q])


def _ros_runs(runs: list[tuple[str, float | None, int]]) -> list[dict]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    os.environ["ROS_DOMAIN_ID"] = str(150 + os.getpid() % 50)
    out = []
    for label, rate, n in runs:
        proc = subprocess.Popen([str(BIN / "posecorr"), "ros2", str(MODEL), "--reliable",
                                 "--registration", "none",   # the poses sent are in the model's frame
                                 "--diagnostics-period", "0.2"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        rclpy.init()
        # Poses go out from this thread; the corrections and diagnostics come back on a node
        # spun by its own executor thread, so that receiving never waits for publishing.
        node = rclpy.create_node("posecorr_bench_source")
        sink = rclpy.create_node("posecorr_bench_sink")
        qos = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_ALL)
        pub = node.create_publisher(PoseStamped, "/tracker/pose", qos)
        back: dict[int, float] = {}
        diags: list[dict[str, str]] = []
        sink.create_subscription(
            PoseStamped, "/tracker/pose_corrected",
            lambda m: back.setdefault(m.header.stamp.nanosec // 1000 + m.header.stamp.sec * 1_000_000,
                                      time.perf_counter()), qos)
        sink.create_subscription(DiagnosticArray, "/diagnostics",
                                 lambda m: diags.append({kv.key: kv.value for kv in m.status[0].values}), 10)
        executor = SingleThreadedExecutor()
        executor.add_node(sink)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        _wait_until(lambda: pub.get_subscription_count() > 0 and diags, 30, 0.05)
        sent_at = _publish(pub, PoseStamped, _poses(n), rate)
        _wait_until(lambda: len(back) >= n, 30, 0.01)
        _wait_until(lambda: diags and diags[-1]["poses_out"] == str(len(back)), 5, 0.05)
        executor.shutdown()
        sink.destroy_node()
        node.destroy_node()
        rclpy.shutdown()
        proc.terminate()
        proc.communicate(timeout=30)
        result = _run_result(label, rate, n, sent_at, back, diags)
        out.append(result)
        print(json.dumps(result), flush=True)
    return out


def _wait_until(done: Callable[[], Any], timeout_s: float, poll_s: float) -> None:
    end = time.monotonic() + timeout_s
    while not done() and time.monotonic() < end:
        time.sleep(poll_s)


def _publish(pub: Any, pose_stamped: type, x: np.ndarray, rate: float | None) -> dict[int, float]:
    """Publishes the poses at `rate` (as fast as possible when None), each stamped with its
    index; returns when each was sent."""
    sent_at: dict[int, float] = {}
    period = 1.0 / rate if rate else 0.0
    start = time.perf_counter()
    for k, p in enumerate(x):
        m = pose_stamped()
        m.header.stamp.sec, m.header.stamp.nanosec = k // 1_000_000, (k % 1_000_000) * 1000
        m.pose.position.x, m.pose.position.y, m.pose.position.z = map(float, p[:3])
        (m.pose.orientation.w, m.pose.orientation.x, m.pose.orientation.y,
         m.pose.orientation.z) = map(float, p[3:])
        sent_at[k] = time.perf_counter()
        pub.publish(m)
        wait = start + (k + 1) * period - time.perf_counter() if period else 0.0
        if wait > 0:  # sleep, not spin: a spinning publisher starves the node of a core
            time.sleep(wait)
    return sent_at


def _run_result(label: str, rate: float | None, n: int, sent_at: dict[int, float],
                back: dict[int, float], diags: list[dict[str, str]]) -> dict:
    """One run's round trips and the node's own last latency report."""
    rtt = np.array([(back[k] - sent_at[k]) * 1e6 for k in back])
    d = diags[-1] if diags else {}
    result = {"run": label, "rate_hz": rate, "poses_sent": n, "poses_back": len(back),
              "node_added_latency": {k.replace("latency_", ""): float(v) for k, v in d.items()
                                     if k.startswith("latency_")},
              "round_trip_through_dds": _stats(rtt)}
    if rate is None and len(back) > 1:
        # steady state: corrections received per second between the first and the last
        times = sorted(back.values())
        result["poses_per_second"] = round((len(times) - 1) / (times[-1] - times[0]), 1)
    return result


def _posecorr_run(n: int) -> dict:
    proc = subprocess.Popen([str(BIN / "posecorr-run"), str(MODEL)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, bufsize=1)
    us = []
    for p in _poses(n):
        line = ",".join(f"{v:.9g}" for v in p) + "\n"
        t = time.perf_counter()
        proc.stdin.write(line)
        proc.stdin.flush()
        proc.stdout.readline()
        us.append((time.perf_counter() - t) * 1e6)
    proc.stdin.close()
    proc.wait(timeout=30)
    return {"run": "posecorr-run through a pipe, one pose at a time", "poses": n,
            "round_trip": _stats(np.array(us))}


def run(path: Path = RESULTS) -> dict:
    load_before = os.getloadavg()
    result = {"model": str(MODEL.relative_to(ROOT)),
              "ros2": _ros_runs([("250 Hz", 250.0, 2500), ("1 kHz", 1000.0, 10_000),
                                 ("unpaced", None, 10_000)]),
              "posecorr_run": _posecorr_run(5000),
              "loadavg_before": [round(v, 2) for v in load_before],
              "loadavg_after": [round(v, 2) for v in os.getloadavg()],
              "cpus": os.cpu_count()}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
