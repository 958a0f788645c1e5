"""Writing files so that nothing a user owns is ever half-written or overwritten by mistake.

* `atomic_output(path)`: the new content goes to a temporary file in the destination's
  folder (an unnamed O_TMPFILE where the file system has it, so that even kill -9 leaves
  nothing behind; else a hidden ``.NAME.*.tmp``), is fsynced, then renamed over the
  destination. A reader (a controller polling a model file) sees the old file or the new
  one, never an empty or truncated one; a full disk fails the write, not the old file.
* `check_output(path, inputs)`: refuses an output that is a folder, sits in a missing or
  read-only folder, or is one of the command's inputs (``fit d.csv -o d.csv``).
* `append_line(path, line)`: appends one whole line under an exclusive lock; a last line
  left torn by an earlier kill is moved to ``PATH.corrupt`` first (and said so on
  stderr), so one interruption costs one record, never the next one glued onto it.
"""
from __future__ import annotations

import contextlib
import errno
import os
import sys
import tempfile
from pathlib import Path
from typing import IO, Any, Iterable, Iterator

try:
    import fcntl
except ImportError:  # Windows: appends are not locked against a second writer
    fcntl = None  # type: ignore[assignment]

__all__ = ["OutputPathError", "Terminated", "append_line", "atomic_output", "check_output",
           "sigterm_as_interrupt", "write_bytes", "write_text"]


class OutputPathError(ValueError):
    """An output path that posecorr refuses to write; the message names the path."""


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_output(path: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str] | None] = ()) -> Path:
    """The output path, or OutputPathError when writing it would fail or destroy an input."""
    out = Path(path)
    if out.is_dir():
        raise OutputPathError(f"{out}: is a folder, expected a file name to write")
    if not str(out.name) or str(out).endswith(os.sep):
        raise OutputPathError(f"{out}: expected a file name to write")
    folder = out.parent if str(out.parent) else Path(".")
    for given in inputs:
        if given is None:
            continue
        source = Path(given)
        if _same_file(out, source) or out.resolve() == source.resolve():
            raise OutputPathError(f"{out}: is also an input or another output of this command; "
                                  "refusing to overwrite it (choose another output name)")
    if not folder.is_dir():
        raise OutputPathError(f"{out}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(f"{out}: folder {folder} is not writable")
    if out.exists() and not os.access(out, os.W_OK):
        raise OutputPathError(f"{out}: file exists and is read-only")
    return out


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


def _unnamed_file(folder: Path) -> int | None:
    """An O_TMPFILE descriptor in `folder` (Linux), or None where unsupported."""
    flag = getattr(os, "O_TMPFILE", None)
    if flag is None:
        return None
    try:
        return os.open(folder, flag | os.O_RDWR, 0o666)
    except OSError:
        return None


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], mode: str = "w", *, encoding: str | None = "utf-8",
                  newline: str | None = "") -> Iterator[IO[Any]]:
    """A file object whose content replaces `path` only when the block ends without error.

    ``mode`` is "w" (text, ``encoding`` and ``newline`` apply) or "wb".
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"mode must be 'w' or 'wb', not {mode!r}")
    out = Path(path)
    folder = out.parent if str(out.parent) else Path(".")
    fd = _unnamed_file(folder)
    named: str | None = None
    if fd is None:
        try:
            fd, named = tempfile.mkstemp(dir=folder, prefix=f".{out.name}.", suffix=".tmp")
        except OSError as exc:
            raise OutputPathError(f"{out}: cannot create a file in {folder}: {exc.strerror}") from None
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
    text = mode == "w"
    handle = os.fdopen(fd, "w" if text else "wb", encoding=encoding if text else None,
                      newline=newline if text else None)
    try:
        try:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
            if named is None:
                named = _link_unnamed(handle.fileno(), folder, out.name)
            os.replace(named, out)
        except OSError as exc:
            if exc.errno not in _DEVICE_ERRORS:
                raise
            raise OutputPathError(f"{out}: cannot write: {exc.strerror}; the previous file is unchanged") from None
        named = None
        _fsync_folder(folder)
    finally:
        handle.close()
        if named is not None:
            with contextlib.suppress(OSError):
                os.unlink(named)


def _link_unnamed(fd: int, folder: Path, name: str) -> str:
    """Give an O_TMPFILE a temporary name beside its destination (for the atomic rename).

    linkat(AT_SYMLINK_FOLLOW) on /proc/self/fd/N; os.link only uses linkat when given a
    folder descriptor. Without /proc the content is copied to a named temporary file.
    """
    folder_fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        for _ in range(100):
            base = f".{name}.{os.getpid()}.{os.urandom(4).hex()}.tmp"
            try:
                os.link(f"/proc/self/fd/{fd}", base, dst_dir_fd=folder_fd, follow_symlinks=True)
                return os.path.join(folder, base)
            except FileExistsError:
                continue
            except OSError:
                break
    finally:
        os.close(folder_fd)
    copy_fd, copy = tempfile.mkstemp(dir=folder, prefix=f".{name}.", suffix=".tmp")
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
    with open(corrupt, "ab") as aside:
        aside.write(torn + b"\n")
        aside.flush()
        os.fsync(aside.fileno())
    handle.truncate(start)
    warn(f"{path}: the last line was cut short by an interrupted write ({len(torn)} bytes); "
         f"moved to {corrupt}")


def append_line(path: str | os.PathLike[str], line: str) -> None:
    """Append `line` plus a newline, durably, repairing a torn last line first."""
    if "\n" in line:
        raise ValueError("append_line takes one line without a newline")
    target = Path(path)
    with open(target, "a+b") as handle:
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
