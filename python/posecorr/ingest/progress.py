"""A progress bar on the terminal while a recording is read: a long one takes tens of
seconds. tqdm draws it on stderr only when stderr is a terminal (a pipe, a log file and the
tests see nothing), and takes it away when the reading ends."""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator


@contextmanager
def progress_bar(total: int, unit: str, what: Path | str) -> Iterator[Callable[[int], None]]:
    """Yields `done(n)`: n of `total` `unit`s of `what` read so far."""
    from tqdm import tqdm

    with tqdm(total=total, unit=unit, unit_scale=True, desc=f"reading {Path(what).name}", disable=None,
              leave=False, dynamic_ncols=True) as bar:
        def done(n: int) -> None:
            bar.update(max(0, min(n, total) - bar.n))

        yield done
