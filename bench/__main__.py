"""`make bench`: every benchmark, JSON results in bench/results/ (timings live here, never in tests).

Run from the repository root: `python -m bench [--only NAME]`.

* `train.json`: seconds per LM epoch of the 9-20-20-20-20-9 network on 2360 samples against
  the torch-levenberg-marquardt package, and the wall time of 30 repeats of the paper's best
  Experiment III configuration (`bench/train.py`).
* `train_small.json`: the default network fitted by trainbr on 12- and 50-pose sessions, its
  damped system solved in error space (the trainers' choice there) and in weight space, in one
  run (`bench/train.py`).
* `fit.json`: wall time of `posecorr fit` on robot-cell tables (36-pose sessions, leave one
  out; 3375 simulated poses), with the load average (`bench/fit.py`).
* `latency.json`: single-pose latency and batch throughput of the shipped zhou MLP in the C
  runtime, the Python shim and onnxruntime (plain and IOBinding), and `pc_run` against a
  hand-written C function of the same network (`bench/latency.py`).
* `targets.json`: the runtime's speed goals as ratios taken in one run: `pc_run` against the
  hand-written zhou MLP (single pose, batch), the demo's physics + PMC model against the
  zhou MLP, the Python shim's single pose (`bench/targets.py`).
* `previous.json`: `pc_run` on one pose against an earlier revision's (c654a8e, before the
  host-floor work), both linked into one process, alternating rounds, quiet and with a
  memcpy on the other core (`bench/previous.py`).
* `floor_all.json`: every table-1 zhou tansig MLP (16 architectures), the 10-10 and 20-20
  MLPs of quat (tansig), eaa (radbas) and R (logsig), and nine networks of widths outside
  table 1 (`OUTSIDE`), against a hand-written AVX2 function
  of the same network (pc_run's bits, `bench/floor/gen_hand.py`): instructions a pose of `pc_run` (this checkout and an
  earlier revision) and of the hand function under callgrind, time ratios with the load
  average, and what each step of a pose runs (`bench/floor_all.py`).
* `apply.json`: `posecorr apply` on 10^6 rows (wall and CPU time, peak memory) against
  the csv module's read-and-write-back floor on the same file (`bench/apply.py`).
* `forms.json`: the loop when the missing effect is outside the catalogue: on simulated
  50-pose sessions with a strain, a bend, an attitude bias or a heading field, what
  `diagnose` proposes, how much of the true form's leave-one-out gain the proposal's file
  recovers, how often null sessions get a proposal, whether sessions with the poses the
  diagnosis asks for show the form (and, without it, nothing), and how long `diagnose` takes
  (`bench/forms.py`).
* `diagnose_workers.json`: `diagnose` on 100, 300 and 600 poses of Experiment II with its
  folds fitted in one process and in two (`--workers`), alternating in one run, and whether
  the two results are the same to the last bit (`bench/diagnose_workers.py`).
* `fit_long.json`: `posecorr fit` on 10^6 rows (wall time, peak memory): refused past
  the rows a fit takes, and fitted on an even draw with `--subsample` (`bench/fit_long.py`).
* `ingest.json`: seconds to ingest a 10-minute recording (300k joint states, 150k tracker
  poses) from a ROS 1 bag, an MCAP file and a CSV log (`bench/ingest.py`).
"""
from __future__ import annotations

import argparse
import json
import sys

from . import RESULTS, latency_model


def _latency() -> dict:
    from . import latency

    return latency.run(RESULTS / "latency.json")


def _targets() -> dict:
    from . import targets

    return targets.run(latency_model(), str(RESULTS / "targets.json"))


def _fit() -> dict:
    from . import fit

    return fit.run(str(RESULTS / "fit.json"))


def _apply() -> dict:
    from . import apply

    return apply.run(str(RESULTS / "apply.json"))


def _train() -> dict:
    from . import train

    return train.run(str(RESULTS / "train.json"))


def _train_small() -> dict:
    from . import train

    return train.run_small(str(RESULTS / "train_small.json"))


def _previous() -> dict:
    from . import previous

    return previous.both(str(RESULTS / "previous.json"))


def _floor_all() -> dict:
    from . import floor_all

    return floor_all.run(str(RESULTS / "floor_all.json"))


def _forms() -> dict:
    from . import forms

    return forms.run(str(RESULTS / "forms.json"))


def _diagnose_workers() -> dict:
    from . import diagnose_workers

    return diagnose_workers.run(str(RESULTS / "diagnose_workers.json"))


def _fit_long() -> dict:
    from . import fit_long

    return fit_long.run(str(RESULTS / "fit_long.json"))


def _ingest() -> dict:
    from . import ingest

    return ingest.run(str(RESULTS / "ingest.json"))


# name -> runner writing bench/results/NAME.json; `make bench` runs them in this order.
BENCHMARKS = {"latency": _latency, "targets": _targets, "previous": _previous,
              "floor_all": _floor_all, "fit": _fit, "fit_long": _fit_long,
              "apply": _apply, "ingest": _ingest, "train": _train, "train_small": _train_small,
              "forms": _forms, "diagnose_workers": _diagnose_workers}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=tuple(BENCHMARKS), help="run one benchmark")
    args = parser.parse_args(argv)
    RESULTS.mkdir(parents=True, exist_ok=True)
    for name, run in BENCHMARKS.items():
        if args.only in (None, name):
            print(json.dumps(run(), indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
