"""Cross-validation folds fitted side by side: `FoldPool`, the processes `pipeline.cross_validate`
hands its folds to.

A fold's fit is independent of the others' and runs the same arithmetic in any process (each
fit is single-threaded, `physics.single_threaded`), so a pool changes how long a
cross-validation takes, never what it gives. The workers are forked: each holds the effects
registered when it forked (user effect files, the forms a diagnosis cuts and registers), and
the pool forks them again when the catalogue has changed since. Where there is no fork
(Windows), the folds are fitted in this process.
"""
from __future__ import annotations

import os
from typing import Any, Callable, Iterable

from posecorr.effects import EFFECTS


def _catalogue() -> tuple:
    """What a worker must hold to fit: every registered effect, by name and identity."""
    return tuple((name, id(EFFECTS[name])) for name in EFFECTS)


class FoldPool:
    """`workers` processes for `map` (one: this process alone). A context manager: leaving it
    ends the workers, at once where it is left by an exception (Ctrl-C)."""

    def __init__(self, workers: int = 1) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
        self.workers = workers if hasattr(os, "fork") else 1
        self._executor: Any = None
        self._forked_with: tuple | None = None

    def map(self, fn: Callable[[Any], Any], tasks: Iterable[Any]) -> list[Any]:
        """[fn(task) for task in tasks], in order; `fn` a module-level function (it is pickled)."""
        tasks = list(tasks)
        if self.workers == 1 or len(tasks) < 2:
            return [fn(task) for task in tasks]
        return list(self._current().map(fn, tasks))

    def _current(self) -> Any:
        from concurrent.futures import ProcessPoolExecutor
        import multiprocessing as mp

        from .protocol import _worker_init

        catalogue = _catalogue()
        if self._executor is not None and self._forked_with != catalogue:
            self._executor.shutdown(wait=True)
            self._executor = None
        if self._executor is None:
            self._executor = ProcessPoolExecutor(max_workers=self.workers, mp_context=mp.get_context("fork"),
                                                 initializer=_worker_init, initargs=(1, os.getpid()))
            self._forked_with = catalogue
        return self._executor

    def close(self, at_once: bool = False) -> None:
        from .protocol import _stop_pool

        if self._executor is not None:
            if at_once:
                _stop_pool(self._executor)
            else:
                self._executor.shutdown(wait=True)
            self._executor = None

    def __enter__(self) -> "FoldPool":
        return self

    def __exit__(self, kind: Any, *_: Any) -> None:
        self.close(at_once=kind is not None)


IN_PROCESS = FoldPool(1)
