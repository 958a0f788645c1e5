"""Writing files so that nothing a user owns is ever half-written or overwritten by mistake.

* `atomic_output(path)`: the new content goes to a temporary file in the destination's
  folder (an unnamed O_TMPFILE where the file system has it, so that even kill -9 leaves
  nothing behind; else a hidden ``.NAME.*.tmp``), is fsynced, then renamed over the
  destination. A reader (a controller polling a model file) sees the old file or the new
  one, never an empty or truncated one; a full disk fails the write, not the old file.
* `check_output(path, inputs)`: refuses an output that is a folder, sits in a missing or
  read-only folder, or is one of the command's inputs (``fit d.csv -o d.csv``).
* `staged_outputs()`: the outputs of one command held until it succeeds, then written
  together; a command failing late leaves none of them.
* `append_line(path, line)`: appends one whole line under an exclusive lock; a last line
  left torn by an earlier kill is moved to ``PATH.corrupt`` first (and said so on
  stderr), so one interruption costs one record, never the next one glued onto it.
* `open_sidecar(path)`: the files posecorr keeps beside a table (ledger, segment list,
  sweep store) are opened without following a symbolic link and only when they are
  regular files: a link would carry the append into another file, a FIFO would block.
"""
from __future__ import annotations

import contextlib
import errno
import os
import stat
import sys
from pathlib import Path
from typing import IO, Any, Callable, Iterable, Iterator

try:
    import fcntl
except ImportError:  # Windows: appends are not locked against a second writer
    fcntl = None  # type: ignore[assignment]

__all__ = ["InUseError", "InputPathError", "OutputPathError", "SidecarError", "Staged", "check_folder_output",
           "check_input", "check_sidecar", "exclusive", "replaced", "Terminated", "append_line", "atomic_output",
           "check_output", "open_sidecar", "sigterm_as_interrupt", "staged_outputs", "write_bytes", "write_text"]


class OutputPathError(ValueError):
    """An output path that posecorr refuses to write; the message names the path."""


class InputPathError(ValueError):
    """An input path that posecorr refuses to read; the message names the path."""


class SidecarError(ValueError):
    """A sidecar (ledger, segment list, sweep store) that is not a regular file."""


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


# Files posecorr keeps beside a table (the ledger of its fits, the segments of its
# ingest, the default sweep store): an input's sidecar is never an output.
SIDECARS = (".ledger.jsonl", ".segments.json", ".sweep.jsonl")


def _kind(mode: int) -> str | None:
    """What a non-regular file is, for the messages; None for a regular file."""
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISLNK, "a symbolic link"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return None


def _lstat(path: Path) -> os.stat_result | None:
    try:
        return os.lstat(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise OutputPathError(f"{path}: {exc.strerror}") from None


def _check_name(path: Path, error: type[ValueError] | None = None) -> None:
    """The C library and the OS would cut the name at a NUL byte and open another file."""
    if "\0" in str(path):
        raise (error or OutputPathError)(f"{str(path)!r}: a file name cannot hold a NUL byte")


def _folder(path: Path) -> OutputPathError:
    """The refusal of a folder given where a file is written."""
    return OutputPathError(f"{path}: is a folder, expected a file name to write")


def check_output(path: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str] | None] = ()) -> Path:
    """The output path, or OutputPathError when writing it would fail or destroy an input:
    only a new path or an existing regular file is written (never a folder, a device, a
    FIFO or a symbolic link, which the atomic rename would replace by a file), and never
    an input, an input's sidecar or another output of the command."""
    out = Path(path)
    _check_name(out)
    if not str(out.name) or str(out).endswith(os.sep):
        raise OutputPathError(f"{out}: expected a file name to write")
    found = _lstat(out)
    kind = None if found is None else _kind(found.st_mode)
    if kind == "a folder":
        raise _folder(out)
    if kind is not None:
        raise OutputPathError(f"{out}: is {kind}; posecorr writes only new or regular files (its atomic "
                              "rename would replace it)")
    folder = out.parent if str(out.parent) else Path(".")
    for given in inputs:
        if given is None:
            continue
        source = Path(given)
        if _same_file(out, source) or out.resolve() == source.resolve():
            raise OutputPathError(f"{out}: is also an input or another output of this command; "
                                  "refusing to overwrite it (choose another output name)")
        for suffix in SIDECARS:
            if out.resolve() == source.resolve().with_name(source.name + suffix):
                raise OutputPathError(f"{out}: is where posecorr keeps the {suffix[1:].split('.')[0]} of input "
                                      f"{source}; refusing to overwrite it (choose another output name)")
    if not folder.is_dir():
        raise OutputPathError(f"{out}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(f"{out}: folder {folder} is not writable")
    if out.exists() and not os.access(out, os.W_OK):
        raise OutputPathError(f"{out}: file exists and is read-only")
    return out


# A table, a model or a recording larger than this is refused before it is read whole.
MAX_INPUT_BYTES = 8 << 30


def check_input(path: str | os.PathLike[str], *, folder_ok: bool = False) -> Path:
    """An input path, or InputPathError: a regular file (or, `folder_ok`, a folder such as a
    ROS 2 bag) that exists and is at most MAX_INPUT_BYTES; a device, a FIFO or a socket
    would be read without end or block forever, and is refused unopened."""
    src = Path(path)
    _check_name(src, InputPathError)
    try:
        found = os.stat(src)
    except FileNotFoundError:
        raise InputPathError(f"{src}: cannot open: No such file or directory") from None
    except OSError as exc:
        raise InputPathError(f"{src}: cannot open: {exc.strerror}") from None
    kind = _kind(found.st_mode)
    if kind == "a folder" and folder_ok:
        return src
    if kind is not None:
        raise InputPathError(f"{src}: is {kind}, expected a file")
    if found.st_size > MAX_INPUT_BYTES:
        raise InputPathError(f"{src}: {found.st_size / 2**30:.1f} GiB, larger than the "
                             f"{MAX_INPUT_BYTES >> 30} GiB posecorr reads")
    return src


# Failures of the device rather than of the caller: reported against the output path.
_DEVICE_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS, errno.EACCES,
                            errno.EPERM})


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems cannot sync a folder; the rename is still atomic
    finally:
        os.close(fd)


def _hidden_name(name: str) -> str:
    return f".{name}.{os.getpid()}.{os.urandom(4).hex()}.tmp"


def _named_file(folder: Path, name: str) -> tuple[int, str]:
    """A new hidden temporary file beside `name`, created as ``open`` creates a file (mode
    0o666 less the umask and what the folder's default ACL takes away): the result keeps
    those permissions when renamed over `name`, and no reading of the umask races a thread."""
    for _ in range(100):
        path = os.path.join(folder, _hidden_name(name))
        try:
            return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666), path
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", os.path.join(folder, f".{name}.*.tmp"))


def _unnamed_file(folder: Path) -> int | None:
    """An O_TMPFILE descriptor in `folder` (Linux), or None where unsupported."""
    flag = getattr(os, "O_TMPFILE", None)
    if flag is None:
        return None
    try:
        return os.open(folder, flag | os.O_RDWR, 0o666)
    except OSError:
        return None


class _Pending:
    """The new content of `path` in a temporary file of its folder (unnamed where the file
    system allows), made visible under `path` by `replace` in one rename."""

    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)
        if self.path.is_dir():   # the rename would fail after the work, in the temporary file's name
            raise _folder(self.path)
        self.folder = self.path.parent if str(self.path.parent) else Path(".")
        self.fd = _unnamed_file(self.folder)
        self.named: str | None = None
        if self.fd is None:
            try:
                self.fd, self.named = _named_file(self.folder, self.path.name)
            except OSError as exc:
                raise OutputPathError(f"{self.path}: cannot create a file in {self.folder}: {exc.strerror}") from None

    def _device(self, exc: OSError) -> OutputPathError:
        return OutputPathError(f"{self.path}: cannot write: {exc.strerror}; the previous file is unchanged")

    def sync(self, handle: IO[Any]) -> None:
        try:
            handle.flush()
            os.fsync(handle.fileno())
        except OSError as exc:
            if exc.errno not in _DEVICE_ERRORS:
                raise
            raise self._device(exc) from None

    def replace(self) -> None:
        try:
            if self.named is None:
                self.named = _link_unnamed(self.fd, self.folder, self.path.name)
            os.replace(self.named, self.path)
        except OSError as exc:
            if exc.errno not in _DEVICE_ERRORS:
                raise
            raise self._device(exc) from None
        self.named = None
        _fsync_folder(self.folder)

    def discard(self) -> None:
        if self.named is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.named)
            self.named = None


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], mode: str = "w", *, encoding: str | None = "utf-8",
                  newline: str | None = "") -> Iterator[IO[Any]]:
    """A file object whose content replaces `path` only when the block ends without error.

    ``mode`` is "w" (text, ``encoding`` and ``newline`` apply) or "wb".
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"mode must be 'w' or 'wb', not {mode!r}")
    pending = _Pending(path)
    text = mode == "w"
    handle = os.fdopen(pending.fd, "w" if text else "wb", encoding=encoding if text else None,
                      newline=newline if text else None)
    try:
        try:
            yield handle
        except OSError as exc:
            if exc.errno not in _DEVICE_ERRORS:
                raise
            raise pending._device(exc) from None
        pending.sync(handle)
        pending.replace()
    finally:
        # After a failed write the buffer still holds bytes that cannot reach the disk:
        # closing would raise again and hide the error that names the file.
        with contextlib.suppress(OSError):
            handle.close()
        pending.discard()


def _link_unnamed(fd: int, folder: Path, name: str) -> str:
    """Give an O_TMPFILE a temporary name beside its destination (for the atomic rename).

    linkat(AT_SYMLINK_FOLLOW) on /proc/self/fd/N; os.link only uses linkat when given a
    folder descriptor. Without /proc the content is copied to a named temporary file.
    """
    folder_fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        for _ in range(100):
            base = _hidden_name(name)
            try:
                os.link(f"/proc/self/fd/{fd}", base, dst_dir_fd=folder_fd, follow_symlinks=True)
                return os.path.join(folder, base)
            except FileExistsError:
                continue
            except OSError:
                break
    finally:
        os.close(folder_fd)
    copy_fd, copy = _named_file(folder, name)
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        while block := os.read(fd, 1 << 20):
            os.write(copy_fd, block)
        os.fsync(copy_fd)
    except BaseException:
        os.unlink(copy)
        raise
    finally:
        os.close(copy_fd)
    return copy


class Staged:
    """The outputs of one command, held until it succeeds (`staged_outputs`)."""

    def __init__(self) -> None:
        self._files: list[tuple[Path, bytes]] = []
        self._then: list[Callable[[], Any]] = []

    def write_bytes(self, path: str | os.PathLike[str], data: bytes) -> None:
        self._files.append((Path(path), bytes(data)))

    def before_replacing(self, step: Callable[[], Any]) -> None:
        """Runs `step` once every content is on disk under a temporary name, before the
        first rename (a ledger line: written only if the files are, and before them)."""
        self._then.append(step)

    def _commit(self) -> None:
        pending: list[_Pending] = []
        try:
            for path, data in self._files:
                pending.append(_Pending(path))
                with os.fdopen(os.dup(pending[-1].fd), "wb", buffering=0) as handle:
                    try:
                        view = memoryview(data)
                        while view:
                            view = view[handle.write(view):]
                    except OSError as exc:
                        if exc.errno not in _DEVICE_ERRORS:
                            raise
                        raise pending[-1]._device(exc) from None
                    pending[-1].sync(handle)
            for step in self._then:
                step()
            for p in pending:
                p.replace()
        finally:
            for p in pending:
                p.discard()
                os.close(p.fd)


@contextlib.contextmanager
def staged_outputs() -> Iterator[Staged]:
    """All or nothing: the block's outputs (`Staged.write_bytes`) are written when it ends
    without error; a command that fails late (an error, SIGTERM, Ctrl-C, SIGKILL) leaves
    none of them and the files they would have replaced unchanged."""
    stage = Staged()
    yield stage
    stage._commit()


def write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    with atomic_output(path, "wb") as handle:
        handle.write(data)


def write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> None:
    with atomic_output(path, "w", encoding=encoding, newline="") as handle:
        handle.write(text)


def warn(message: str) -> None:
    print(f"posecorr: warning: {message}", file=sys.stderr, flush=True)


def _repair_torn_tail(handle: IO[bytes], path: Path) -> None:
    """Move a last line without its newline to PATH.corrupt and cut it off."""
    size = handle.seek(0, os.SEEK_END)
    if size == 0:
        return
    handle.seek(size - 1)
    if handle.read(1) == b"\n":
        return
    start, block = size, 1 << 16
    while start > 0:
        begin = max(0, start - block)
        handle.seek(begin)
        chunk = handle.read(start - begin)
        cut = chunk.rfind(b"\n")
        if cut >= 0:
            start = begin + cut + 1
            break
        start = begin
    handle.seek(start)
    torn = handle.read()
    corrupt = path.with_name(path.name + ".corrupt")
    with open_sidecar(corrupt, append=True) as aside:
        aside.write(torn + b"\n")
        aside.flush()
        os.fsync(aside.fileno())
    handle.truncate(start)
    warn(f"{path}: the last line was cut short by an interrupted write ({len(torn)} bytes); "
         f"moved to {corrupt}")


def _sidecar_refused(path: Path, kind: str) -> SidecarError:
    return SidecarError(f"{path}: is {kind}; posecorr reads and writes this file only as a regular file, "
                        "never through a link or a special file (remove or rename it)")


def check_sidecar(path: str | os.PathLike[str]) -> Path:
    """The sidecar's path when it is missing or a regular file, else SidecarError: a
    command checks it before any work (`open_sidecar` checks again when it opens)."""
    target = Path(path)
    try:
        found = os.lstat(target)
    except FileNotFoundError:
        return target
    except OSError as exc:
        raise SidecarError(f"{target}: cannot open: {exc.strerror}") from None
    kind = _kind(found.st_mode)
    if kind is not None:
        raise _sidecar_refused(target, kind)
    return target


def open_sidecar(path: str | os.PathLike[str], *, append: bool = False) -> IO[bytes] | None:
    """A sidecar opened without following a link (O_NOFOLLOW) and without blocking on a
    FIFO (O_NONBLOCK), refused with SidecarError unless it is a regular file: "rb", or
    with `append` "a+b" (created when missing). Reading a missing sidecar gives None."""
    target = Path(path)
    flags = getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    flags |= os.O_RDWR | os.O_CREAT | os.O_APPEND if append else os.O_RDONLY
    try:
        fd = os.open(target, flags, 0o666)
    except FileNotFoundError:
        if append:
            raise SidecarError(f"{target}: cannot create: folder {target.parent} does not exist") from None
        return None
    except OSError as exc:
        check_sidecar(target)  # a link (ELOOP), a FIFO without reader (ENXIO): named as such
        raise SidecarError(f"{target}: cannot open: {exc.strerror}") from None
    kind = _kind(os.fstat(fd).st_mode)
    if kind is not None:
        os.close(fd)
        raise _sidecar_refused(target, kind)
    os.set_blocking(fd, True)
    return os.fdopen(fd, "a+b" if append else "rb")


def append_line(path: str | os.PathLike[str], line: str) -> None:
    """Append `line` plus a newline, durably, repairing a torn last line first; the file
    is a sidecar (`open_sidecar`): a link or a special file is refused."""
    if "\n" in line:
        raise ValueError("append_line takes one line without a newline")
    target = Path(path)
    with open_sidecar(target, append=True) as handle:
        if fcntl is not None:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
        try:
            _repair_torn_tail(handle, target)
            handle.seek(0, os.SEEK_END)
            handle.write(line.encode("utf-8") + b"\n")
            handle.flush()
            os.fsync(handle.fileno())
        finally:
            if fcntl is not None:
                fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


def check_folder_output(path: str | os.PathLike[str], marker: str, what: str) -> Path:
    """A folder a command replaces whole: new, empty, or one it wrote before (holding
    `marker`); any other folder, or a file, is refused before any work."""
    out = Path(path)
    _check_name(out)
    found = _lstat(out)
    if found is None:
        return out
    if not stat.S_ISDIR(found.st_mode):
        raise OutputPathError(f"{out}: exists and is not a folder; {what} is a folder")
    if any(out.iterdir()) and not (out / marker).exists():
        raise OutputPathError(f"{out}: is a folder that does not hold {what} (no {marker}); refusing to "
                              "replace its files (choose a new name)")
    return out


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # another user's process: alive
    return True


def _remove_stale_partials(folder: Path, out: Path) -> None:
    """What `replaced` left beside `out` in a run killed with SIGKILL (no clean-up can run
    then): removed, and said so, once the process that wrote it is gone."""
    import re
    import shutil

    pattern = re.compile(rf"\.{re.escape(out.stem)}\.(\d+)\.[0-9a-f]{{8}}\.partial{re.escape(out.suffix)}")
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for entry in entries:
        found = pattern.fullmatch(entry.name)
        if found is None or _alive(int(found.group(1))):
            continue
        if entry.is_dir(follow_symlinks=False):
            shutil.rmtree(entry.path, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                os.unlink(entry.path)
        warn(f"{entry.path}: removed, left by an interrupted run (process {found.group(1)}, now gone)")


@contextlib.contextmanager
def replaced(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A fresh hidden path beside `path`, with its suffix, for a writer that creates a file
    or a folder by name; what it wrote takes `path`'s place in one rename when the block
    ends without error (a folder: the old one is renamed away first, then removed), and is
    removed otherwise. A killed command leaves the previous `path` whole; after SIGKILL its
    hidden ``.STEM.PID.*.partial`` stays until the next run on `path` removes it."""
    import shutil

    out = Path(path)
    folder = out.parent if str(out.parent) else Path(".")
    _remove_stale_partials(folder, out)
    fresh = folder / f".{out.stem}.{os.getpid()}.{os.urandom(4).hex()}.partial{out.suffix}"
    old = None
    try:
        yield fresh
        if fresh.is_dir() and out.is_dir():
            old = folder / f".{out.name}.{os.getpid()}.{os.urandom(4).hex()}.old"
            os.rename(out, old)
        os.replace(fresh, out)
        _fsync_folder(folder)
    finally:
        for leftover in (fresh, old):
            if leftover is not None and os.path.lexists(leftover):
                if leftover.is_dir() and not leftover.is_symlink():
                    shutil.rmtree(leftover, ignore_errors=True)
                else:
                    with contextlib.suppress(OSError):
                        os.unlink(leftover)


class InUseError(OSError):
    """Another posecorr process holds the file (`exclusive`)."""


@contextlib.contextmanager
def exclusive(path: str | os.PathLike[str]) -> Iterator[None]:
    """Holds a lock beside `path` (a hidden ``.NAME.lock``, removed after) for the block:
    a second process asking for it fails at once with InUseError, instead of both writing
    the same file (two sweeps on one store would run every configuration twice)."""
    out = Path(path)
    if fcntl is None:
        yield
        return
    lock = out.with_name(f".{out.name}.lock")
    fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0), 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InUseError(f"{out}: in use by another posecorr process (lock {lock}); "
                             "wait for it to finish") from None
        try:
            yield
        finally:
            with contextlib.suppress(OSError):
                os.unlink(lock)
    finally:
        os.close(fd)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that the same clean-up runs (temporary files
    dropped, pool workers stopped, finished work kept)."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated()


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises `Terminated` (main thread only; a handler someone
    else installed is left alone)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, _raise_terminated):
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
