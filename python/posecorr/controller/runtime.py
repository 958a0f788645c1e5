"""Apply an exported posecorr corrector (.onnx) from Python.

`Corrector(path, backend="c")` runs the model through libposecorr (the dependency-free C
runtime) via ctypes, a single pose through the optional extension `_call1` when it was
built; `backend="onnxruntime"` runs the same file through onnxruntime, with the same API
and the same checks (`checks`: what libposecorr refuses at load and per call, this back end
refuses with the same status and message). Only numpy and ctypes are imported here;
onnxruntime is imported lazily.

Outputs are float64 arrays of the caller's shape ((7,) or (N, 7)); the model computes in
float32, so values carry float32 precision. A model with a time-dependent effect (drift)
has a second input `t` (s since the session's start, `Corrector.takes_time`); `correct`
passes `t=` to it on both backends, and t = 0 for every pose when `t` is not given.

The library is looked up in ``posecorr/_native/libposecorr.so`` (placed there by the
package build), else in ``$POSECORR_LIBRARY``.

Threads: one `Corrector` may be shared by any number of threads; concurrent calls return
the bits one thread would get. A C-backed model has one arena (pc_run writes its buffers,
runtime_c/posecorr.h), so its calls take a lock and run one at a time; onnxruntime's
session runs concurrent calls itself. For calls that should run in parallel, give each
thread its own `Corrector` of the same file. `close` waits for a running call; a call after
it raises PoseCorrError ("... is closed").
"""
from __future__ import annotations

import ctypes
import os
import threading
from pathlib import Path
from typing import Any

import numpy as np

from . import checks
from .checks import PoseCorrError

__all__ = ["Corrector", "PoseCorrError", "load_library", "library_path"]

POSE_WIDTH = 7
TIME_INPUT = checks.TIME_INPUT
_MESSAGE_SIZE = 256
MAX_MAX_BATCH = 4096  # PC_MAX_MAX_BATCH
# libposecorr's PC_VERSION_MAJOR, PC_VERSION_MINOR this shim is written against: the
# library must have the same major and at least this minor (minors add functions and, at
# 0.4, fields at the end of pc_options; 0.5 checks times and input quaternions, the
# checks of `checks`; 0.6 the digest, the reach, the PC_LOAD_ALLOW_* flags and
# the step path report).
EXPECTED_VERSION = (0, 6)
# posecorr.h's pc_options.flags the shim passes (Corrector's allow_* arguments).
_ALLOW_UNBOUNDED, _ALLOW_UNSIGNED = 1 << 4, 1 << 5


def _call1_module() -> Any:
    """posecorr.controller._call1 (the optional single-pose extension), or None when not built."""
    try:
        from . import _call1
    except ImportError:
        return None
    return _call1


class _Error(ctypes.Structure):
    _fields_ = [("status", ctypes.c_int), ("message", ctypes.c_char * _MESSAGE_SIZE)]


class _Options(ctypes.Structure):
    _fields_ = [("max_batch", ctypes.c_size_t), ("flags", ctypes.c_uint),
                ("program_ops", ctypes.c_size_t)]


_LIBS: dict[str, ctypes.CDLL] = {}


def library_path() -> Path:
    """Path of libposecorr that `Corrector` uses."""
    here = Path(__file__).resolve().parents[1] / "_native"  # posecorr/_native, beside this package
    for name in ("libposecorr.so", "libposecorr.dylib"):
        if (here / name).exists():
            return here / name
    env = os.environ.get("POSECORR_LIBRARY")
    if env:
        return Path(env)
    raise PoseCorrError(
        f"libposecorr not found in {here} and $POSECORR_LIBRARY is not set; "
        "reinstall posecorr (pip install -e .) to build the C runtime")


def load_library(path: str | os.PathLike | None = None) -> ctypes.CDLL:
    """Loads libposecorr once per path and declares the C signatures."""
    p = str(path if path is not None else library_path())
    lib = _LIBS.get(p)
    if lib is not None:
        return lib
    lib = ctypes.CDLL(p)
    check_version(lib, p)
    vp, sz, cp = ctypes.c_void_p, ctypes.c_size_t, ctypes.c_char_p
    lib.pc_load_file.argtypes = [cp, ctypes.POINTER(_Options), ctypes.POINTER(vp),
                                 ctypes.POINTER(_Error)]
    lib.pc_load_file.restype = ctypes.c_int
    lib.pc_load_memory.argtypes = [cp, sz, ctypes.POINTER(_Options), ctypes.POINTER(vp),
                                   ctypes.POINTER(_Error)]
    lib.pc_load_memory.restype = ctypes.c_int
    lib.pc_free.argtypes = [vp]
    lib.pc_free.restype = None
    lib.pc_run.argtypes = [vp, vp, sz, vp]
    lib.pc_run.restype = ctypes.c_int
    lib.pc_run_timed.argtypes = [vp, vp, vp, sz, vp]
    lib.pc_run_timed.restype = ctypes.c_int
    lib.pc_model_takes_time.argtypes = [vp]
    lib.pc_model_takes_time.restype = ctypes.c_int
    lib.pc_model_message.argtypes = [vp]
    lib.pc_model_message.restype = cp
    lib.pc_status_name.argtypes = [ctypes.c_int]
    lib.pc_status_name.restype = cp
    lib.pc_metadata_count.argtypes = [vp]
    lib.pc_metadata_count.restype = sz
    for fn in (lib.pc_metadata_key, lib.pc_metadata_value):
        fn.argtypes = [vp, sz]
        fn.restype = cp
    for fn in (lib.pc_max_batch, lib.pc_arena_bytes, lib.pc_step_count, lib.pc_node_count):
        fn.argtypes = [vp]
        fn.restype = sz
    lib.pc_model_step_path.argtypes = [vp, sz, ctypes.POINTER(ctypes.c_int), cp, sz]
    lib.pc_model_step_path.restype = ctypes.c_int
    lib.pc_path_name.argtypes = [ctypes.c_int]
    lib.pc_path_name.restype = cp
    _LIBS[p] = lib
    return lib


def check_version(lib: ctypes.CDLL, path: str) -> None:
    """Refuses a libposecorr whose pc_version() does not fit EXPECTED_VERSION."""
    try:
        fn = lib.pc_version
    except AttributeError:
        number = None
    else:
        fn.argtypes, fn.restype = [], ctypes.c_int
        number = fn()
    if not version_compatible(number):
        found = "no pc_version()" if number is None else \
            f"{number // 10000}.{number // 100 % 100}.{number % 100}"
        raise PoseCorrError(f"{path}: libposecorr {found}, this posecorr needs "
                            f"{EXPECTED_VERSION[0]}.{EXPECTED_VERSION[1]} or a later "
                            f"{EXPECTED_VERSION[0]}.x; reinstall posecorr (pip install -e .)")


def version_compatible(number: int | None) -> bool:
    """Whether a pc_version() number (major*10000 + minor*100 + patch) fits."""
    if number is None:
        return False
    return number // 10000 == EXPECTED_VERSION[0] and number // 100 % 100 >= EXPECTED_VERSION[1]


class _CBackend:
    def __init__(self, path: str | os.PathLike | bytes, library: str | os.PathLike | None,
                 max_batch: int, flags: int = 0) -> None:
        self.lib = lib = load_library(library)
        # pc_run writes the model's one arena (and _in1/_out1 are shared): one call at a
        # time, whichever thread; ctypes releases the GIL, so the GIL alone does not do it.
        self._lock = threading.Lock()
        self.name = _where(path)
        handle = ctypes.c_void_p()
        err = _Error()
        opts = _Options(int(max_batch), flags)
        if isinstance(path, bytes):
            st = lib.pc_load_memory(path, len(path), ctypes.byref(opts), ctypes.byref(handle),
                                    ctypes.byref(err))
        else:
            _check_file(path)
            st = lib.pc_load_file(os.fsencode(path), ctypes.byref(opts), ctypes.byref(handle),
                                  ctypes.byref(err))
        if st != 0:
            raise PoseCorrError(f"{_where(path)}: {err.message.decode(errors='replace')}", st)
        self.handle = handle.value
        # Single-pose path: fixed buffers and raw addresses, so a call is one copy in,
        # one foreign call and one copy out.
        self._in1 = np.zeros(POSE_WIDTH, dtype=np.float32)
        self._out1 = np.zeros(POSE_WIDTH, dtype=np.float32)
        self._in1_ptr = self._in1.ctypes.data
        self._out1_ptr = self._out1.ctypes.data
        self._run = lib.pc_run
        # The single-pose fast path (posecorr.controller._call1) when it was built: pc_run's address
        # and the model's, passed as ints, no ctypes conversion per call.
        self._call1 = _call1_module()
        self._run_address = ctypes.cast(lib.pc_run, ctypes.c_void_p).value
        n = lib.pc_metadata_count(self.handle)
        self.metadata = {lib.pc_metadata_key(self.handle, i).decode(errors="replace"):
                         lib.pc_metadata_value(self.handle, i).decode(errors="replace")
                         for i in range(n)}
        self.max_batch = int(lib.pc_max_batch(self.handle))
        self.arena_bytes = int(lib.pc_arena_bytes(self.handle))
        self.n_steps = int(lib.pc_step_count(self.handle))
        self.n_nodes = int(lib.pc_node_count(self.handle))
        self.takes_time = bool(lib.pc_model_takes_time(self.handle))

    @property
    def limits(self) -> checks.Limits:
        """What pc_run checks, read from the metadata for the one refusal the shim makes
        itself (a value beyond float32's range, Corrector.correct)."""
        return checks.Limits.from_metadata(self.metadata, self.takes_time, allow_unbounded=True)

    def step_paths(self) -> list[tuple[str, str]]:
        """(path, why) of each step of the one-pose plan: "specialised", "general" or
        "interpreted", and what the step is and why it runs that path."""
        out = []
        path, why = ctypes.c_int(), ctypes.create_string_buffer(256)
        for i in range(self.n_steps):
            st = self.lib.pc_model_step_path(self.handle, i, ctypes.byref(path), why, len(why))
            if st:
                raise self._fail(st)
            name = self.lib.pc_path_name(path.value).decode()
            out.append((name, why.value.decode(errors="replace")))
        return out

    def _fail(self, st: int) -> PoseCorrError:
        msg = self.lib.pc_model_message(self.handle).decode(errors="replace")
        name = self.lib.pc_status_name(st).decode()
        return PoseCorrError(f"{name}: {msg}", st)

    def _open(self) -> int:
        """The model's handle; called under the lock."""
        if self.handle is None:
            raise _closed(self.name)
        return self.handle

    def run1(self, pose: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        if t is not None:
            return self.run(np.reshape(pose, (1, POSE_WIDTH)), t)[0]
        with self._lock:
            handle = self._open()
            if self._call1 is not None:
                out = np.empty(POSE_WIDTH)
                st = self._call1.run1(self._run_address, handle, pose, out)
                if st == 0:
                    return out
                if st > 0:
                    raise self._fail(st)
                # st < 0: not a float64 contiguous (7,) array; the general path converts it
            self._in1[:] = _float32(pose)
            st = self._run(handle, self._in1_ptr, 1, self._out1_ptr)
            if st:
                raise self._fail(st)
            return self._out1.astype(np.float64)

    def run1_f32(self, pose: np.ndarray, out: np.ndarray) -> None:
        """Lowest-overhead form: float32 contiguous (7,) in and out, caller-owned."""
        with self._lock:
            st = self._run(self._open(), pose.ctypes.data, 1, out.ctypes.data)
            if st:
                raise self._fail(st)

    def run(self, poses: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        x = _float32(poses)
        out = np.empty_like(x)
        tt = None if t is None else _float32(t)
        with self._lock:
            handle = self._open()
            if tt is None:
                st = self._run(handle, x.ctypes.data, x.shape[0], out.ctypes.data)
            else:
                st = self.lib.pc_run_timed(handle, x.ctypes.data, tt.ctypes.data, x.shape[0],
                                           out.ctypes.data)
            if st:
                raise self._fail(st)
        return out.astype(np.float64)

    def close(self) -> None:
        if not hasattr(self, "_lock"):
            return  # the library failed to load: nothing was allocated
        with self._lock:  # waits for a call that is running
            if getattr(self, "handle", None):
                self.lib.pc_free(self.handle)
            self.handle = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


def _float32(values: np.ndarray) -> np.ndarray:
    """`values` as contiguous float32 for the model. A finite value beyond float32's range
    becomes inf, refused as not finite and then named as given (Corrector.correct): numpy's
    warning about the cast would only say it first, and less well."""
    if values.dtype == np.float32:
        return np.ascontiguousarray(values)
    with np.errstate(over="ignore"):
        return np.ascontiguousarray(values, dtype=np.float32)


def _closed(name: str) -> PoseCorrError:
    return PoseCorrError(f"{name}: the Corrector is closed (close() was called); load the model again")


def _check_file(path: str | os.PathLike) -> None:
    """A model path must be a regular file, refused in the command line's words otherwise:
    a FIFO would block the load forever, a folder or a device would read as nonsense."""
    from ..safeio import InputPathError, check_input

    try:
        check_input(path)
    except InputPathError as exc:
        raise PoseCorrError(str(exc), int(checks.Status.IO)) from None


def _where(path: str | os.PathLike | bytes) -> str:
    """How a load error names the model."""
    return f"model of {len(path)} bytes" if isinstance(path, bytes) else os.fspath(path)


class _OrtBackend:
    """onnxruntime behind libposecorr's checks (`checks`): the model is checked at load as
    the C loader checks it, and every call's input and output as pc_run checks them."""

    def __init__(self, path: str | os.PathLike | bytes, allow_unbounded: bool = False,
                 allow_unsigned: bool = False) -> None:
        import onnxruntime as ort  # only for this backend

        name = _where(path)
        if isinstance(path, bytes):
            data = path
        else:
            _check_file(path)
            try:
                data = Path(path).read_bytes()
            except OSError as exc:
                raise PoseCorrError(f"{name}: cannot read it ({exc.strerror})", int(checks.Status.IO)) from None
        # What libposecorr refuses at load is refused before onnxruntime sees the bytes.
        self.metadata, self.limits = checks.check_model(data, name, allow_unbounded, allow_unsigned)
        so = ort.SessionOptions()
        so.intra_op_num_threads = 1
        so.inter_op_num_threads = 1
        # A file onnxruntime cannot load is named in one line below; its own log would print
        # the same failure again on stderr, in colour, before it.
        so.log_severity_level = 4
        try:
            self.session = ort.InferenceSession(data, so, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime's own exception types, one per failure kind
            raise PoseCorrError(f"{name}: onnxruntime cannot load it: {_first_line(exc)}") from None
        self.name = name
        self.max_batch = None
        self.takes_time = TIME_INPUT in {i.name for i in self.session.get_inputs()}

    def run(self, poses: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        # InferenceSession.run is safe from several threads: no lock here.
        session = self.session
        if session is None:
            raise _closed(self.name)
        x = _float32(poses)
        tt = None if t is None else _float32(t)
        checks.check_input(self.limits, x, tt)
        feeds = {"pose": x}
        if self.takes_time:
            feeds[TIME_INPUT] = np.zeros(len(x), np.float32) if tt is None else tt
        try:
            out = session.run(["corrected"], feeds)[0]
        except Exception as exc:   # named as pc_run names its faults: the status, not the file
            raise checks.failure(checks.Status.RUNTIME, f"onnxruntime failed to run it: {_first_line(exc)}") from None
        if out.shape != x.shape:
            raise checks.failure(checks.Status.RUNTIME, f"output 'corrected' has shape {list(out.shape)}, "
                                                        f"expected {list(x.shape)}")
        checks.check_output(self.limits, x, out)
        return out.astype(np.float64)

    def run1(self, pose: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
        return self.run(_float32(pose).reshape(1, POSE_WIDTH), t)[0]

    def close(self) -> None:
        self.session = None


def _first_line(exc: BaseException) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


def _real(values: Any, what: str) -> np.ndarray:
    """`values` as an array of real numbers; complex ones would lose their imaginary part
    and strings or objects would fail deep in a conversion."""
    a = np.asarray(values)
    if a.dtype.kind not in "iuf":
        raise ValueError(f"{what} must be real numbers (float or int), got an array of {a.dtype}")
    return a


def _loaded(path: Any, backend: str, options: dict[str, Any]) -> "Corrector":
    """A Corrector made again from its arguments (`Corrector.__reduce__`)."""
    return Corrector(path, backend, **options)


class Corrector:
    """An exported corrector: ``Corrector("model.onnx").correct(poses)``.

    Parameters
    ----------
    path: the .onnx file, or its bytes (bytes, bytearray or memoryview).
    backend: ``"c"`` (libposecorr, default) or ``"onnxruntime"``.
    library: explicit libposecorr path for the C backend (default: see module doc).
    max_batch: poses evaluated per C call, 1 to 4096 (chunking is internal; any N works).
    allow_unbounded: load a model without metadata input_bounds or correction_reach (another
      producer's): its poses are then not checked against them. Refused otherwise.
    allow_unsigned: load a model without metadata model_digest. Refused otherwise; a
      digest that is present is always verified (docs/design.md, "The ONNX contract").

    One Corrector may be shared by threads (see the module doc): concurrent calls give the
    bits of one thread; on the C back end they run one at a time under a lock.
    """

    def __init__(self, path: str | os.PathLike | bytes | bytearray | memoryview, backend: str = "c", *,
                 library: str | os.PathLike | None = None, max_batch: int = 256,
                 allow_unbounded: bool = False, allow_unsigned: bool = False) -> None:
        if backend not in ("c", "onnxruntime"):
            raise ValueError(f"backend must be 'c' or 'onnxruntime', not {backend!r}")
        if isinstance(max_batch, bool) or not isinstance(max_batch, (int, np.integer)) \
                or not 1 <= max_batch <= MAX_MAX_BATCH:
            raise ValueError(f"max_batch must be an integer from 1 to {MAX_MAX_BATCH}, not {max_batch!r}")
        # Model bytes as one immutable copy, whatever held them: the back ends and the errors
        # read bytes, and a later change to the caller's buffer cannot reach the loaded model.
        if isinstance(path, (bytearray, memoryview)):
            path = bytes(path)
        self.path = path if isinstance(path, bytes) else Path(path)
        self.backend = backend
        self._options = {"library": library, "max_batch": max_batch, "allow_unbounded": allow_unbounded,
                         "allow_unsigned": allow_unsigned}
        if backend == "c":
            flags = (_ALLOW_UNBOUNDED if allow_unbounded else 0) | (_ALLOW_UNSIGNED if allow_unsigned else 0)
            self._impl: Any = _CBackend(path, library, max_batch, flags)
        else:
            self._impl = _OrtBackend(path, allow_unbounded, allow_unsigned)
        self.metadata: dict[str, str] = dict(self._impl.metadata)
        self.n_inputs = POSE_WIDTH
        self.n_outputs = POSE_WIDTH
        self.input_name = "pose"
        self.output_name = "corrected"
        # The model has the input `t` (a time-dependent effect such as drift).
        self.takes_time: bool = self._impl.takes_time

    def __reduce__(self) -> tuple:
        # a loaded library and model are no data: a copy (pickle, deepcopy, a worker process)
        # loads the model again from what this one was given, its checks included
        return _loaded, (self.path, self.backend, self._options)

    def correct(self, poses: Any, t: Any = None) -> np.ndarray:
        """Corrects one pose (7,) or a batch (N, 7): x, y, z, qw, qx, qy, qz.

        t: time of each pose, s since the session's start (a scalar for one pose, (N,) for
        a batch); used by models that take time (`takes_time`), ignored by the others.
        Without it such a model corrects every pose as at t = 0, the session's start.
        Returns float64 of the same shape. Raises PoseCorrError (its `status` is
        libposecorr's) for what either back end refuses: NaN/inf, a position outside the
        model's input_bounds, a time outside its time_bounds, a value beyond float32's range
        (where the model has no bounds), a quaternion that is not unit, a result that is not
        a pose.
        """
        a = _real(poses, "poses")
        single = a.shape == (POSE_WIDTH,)
        if not single and (a.ndim != 2 or a.shape[1] != POSE_WIDTH):
            raise ValueError(f"poses must have shape (7,) or (N, 7), got {a.shape}")
        if t is not None:
            t = _real(t, "t").astype(np.float64)
            if t.shape != (() if single else (a.shape[0],)):
                raise ValueError(f"t must have shape {'()' if single else (a.shape[0],)} "
                                 f"for poses of shape {a.shape}, got {t.shape}")
            if not self.takes_time:
                t = None
        try:
            if single:
                return self._impl.run1(a, None if t is None else t.reshape(1))
            if a.shape[0] == 0:
                return np.zeros((0, POSE_WIDTH))
            return self._impl.run(a, t)
        except PoseCorrError as exc:
            if exc.status != checks.Status.NONFINITE:
                raise
            refused = exc
        # Checked only once refused, so that a float64 pose costs nothing more: a finite value
        # beyond float32's range reached the model as inf, and is named here as the caller gave it.
        checks.check_wide_input(self._impl.limits, a.reshape(-1, POSE_WIDTH), None if t is None else t.reshape(-1))
        raise refused

    def step_paths(self) -> list[tuple[str, str]]:
        """What each step of a pose runs in libposecorr: [(path, why)], path "specialised"
        (code for its shape), "general" or "interpreted" (C back end only)."""
        if self.backend != "c":
            raise ValueError("step paths describe libposecorr's plan: use backend='c'")
        return self._impl.step_paths()

    def predict(self, measured: Any, t: Any = None) -> np.ndarray:
        """scikit-learn style alias of `correct`: one pose (7,) or a batch (N, 7).

        t: time of each pose, s since the session's start (a scalar for one pose, (N,) for
        a batch); used by models that take time (`takes_time`), ignored by the others.
        Without it such a model corrects every pose as at t = 0, the session's start.
        """
        return self.correct(measured, t)

    __call__ = correct

    def close(self) -> None:
        self._impl.close()

    def __enter__(self) -> "Corrector":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        # A model given as bytes is named as its load errors name it, not by 65 kB of escapes.
        model = repr(str(self.path)) if isinstance(self.path, Path) else f"<{_where(self.path)}>"
        return f"Corrector({model}, backend={self.backend!r})"
