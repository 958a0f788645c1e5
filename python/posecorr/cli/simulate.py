"""`posecorr simulate`."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from . import options
from .common import (TABLE, Verb, CliError, effect_file_option, effects_help, emit, load_effect_files, output_option,
                     seed_option)


# The options of a drawn session (`--session`), which an experiment's table does not take.
SESSION_OPTIONS = ("poses", "spread", "position_only", "unremovable", "robot", "duration")
DEFAULT_TARGETS = 40


def add_arguments(p: argparse.ArgumentParser) -> None:
    from ..kinematics import UR_ARMS

    p.add_argument("--experiment", type=int, choices=(1, 2, 3), help="the paper's experiment I, II or III")
    p.add_argument("--session", action="store_true",
                   help="a realistic session: 6-40 poses unless --poses or --robot (30-60) says otherwise, the "
                        "tracker's own frame, a lever arm (drawn from --seed); --effects adds effects in the cell")
    p.add_argument("--poses", type=options.integer(6, 100_000), metavar="N",
                   help="with --session: number of poses, 6..100,000 (default: drawn)")
    p.add_argument("--spread", help="with --session: orientation spread none, yaw or full")
    p.add_argument("--position-only", action=argparse.BooleanOptionalAction,
                   help="with --session: no reference orientation; --no-position-only: a full-pose reference "
                        "(default: drawn, position only in 25 %% of sessions set down by hand, never with a robot)")
    p.add_argument("--unremovable", type=options.real(0, 1000),
                   help="with --session: RMS (mm) of an error no model removes (default: drawn, 0 in 85 %% of "
                        "sessions set down by hand, else 60-110 mm; 0 with a robot)")
    p.add_argument("--robot", help=f"with --session: a robot arm ({', '.join(UR_ARMS)}) carries the tracker on its "
                                   "flange through 30-60 poses of every orientation; none: a tracker set down by "
                                   "hand (default: drawn, a ur5e or the KUKA-sized ur10e in 15 %% of sessions, none "
                                   "where --spread is none or yaw)")
    p.add_argument("--duration", type=options.real(1.0, 1e8), metavar="SECONDS",
                   help="with --session: the session's length; the table gets a time column t, the poses evenly "
                        "spaced (a drift or another time-dependent effect needs it; a robot takes about 40 s a pose)")
    p.add_argument("--effects", help=effects_help(
        "override or add effects: NAME=V1,V2,...;NAME;NAME=off, values in parameter order; effects are "
        "separated by ';' as values take ',' (bare names may also be separated by ',': sweep,range_scale)",
        fitted=False))
    p.add_argument("--only", action="store_true",
                   help="with --experiment: start from nothing, not the default mix: only the --effects given and an "
                        "--effect-file's effects act (no noise unless noise is named)")
    p.add_argument("--station-pose", type=options.station_pose, metavar="POSE",
                   help="where the base station stands, in the reference frame: paper (the paper's, eq. 23) or "
                        "x,y,z[,qw,qx,qy,qz] (m, unit quaternion; the station looks along its -z); simulate prints "
                        "where it stands in the tracker's own frame, as --station-pose tracker:... takes it "
                        "(default: paper)")
    effect_file_option(p)
    seed_option(p)
    output_option(p, help="the paired-pose table (CSV) to write")
    p.add_argument("--recording", type=Path, metavar="OUT.(bag|mcap|csv)",
                   help="also write the recording behind the table: ROS 1 .bag, .mcap, .csv, or a name without "
                        "suffix for a ROS 2 bag directory; -o then holds the recorded poses only")
    p.add_argument("--targets", type=options.integer(1, 10_000),
                   help=f"poses visited by --recording, first of the measurement order (default {DEFAULT_TARGETS}: 7 "
                        "minutes)")


# The first line of every table simulate writes: what it may replace (`failures`), for a
# table of measurements under the same name would be lost.
MARK = "written by posecorr simulate"


def run(args: argparse.Namespace) -> None:
    from ..data import write_table
    from ..simulate import simulate
    from ..textui import METRIC_HEADERS, metrics_rows, table

    files = load_effect_files(args)  # before parsing: --effects may name the file's effects
    effects = _effects(args.effects)
    if args.recording is not None:
        from ..recording import check_recording_output
        from ..safeio import OutputPathError

        check_recording_output(args.recording)
        if args.recording.resolve() == args.output.resolve():
            raise OutputPathError(f"{args.recording}: is also -o; the recording and its table are two files")
    _check_kind(args)
    if args.session:
        if args.recording is not None:
            raise CliError("--recording drives the robot through an experiment's targets: give --experiment N")
        result = _simulate_session(args, effects or {})
    else:
        result = simulate(args.experiment, effects=effects, seed=args.seed, effect_files=files,
                          base="none" if args.only else "default", station_pose=_station_pose(args))
    sim_table, raw, floor = result.table, result.raw, result.noise_floor
    recording = None
    if args.recording is not None:
        from ..recording import simulate_recording, table_metrics, write_recording

        recording = simulate_recording(result, n_targets=args.targets or DEFAULT_TARGETS, seed=args.seed)
        write_recording(recording, args.recording)
        sim_table = recording.table
        raw, floor = table_metrics(result, sim_table.n)
    write_table(sim_table, args.output, comment=f"{MARK} (seed {args.seed}): simulated poses, not measurements")
    effects_used = result.effects_json()
    payload = {"n": sim_table.n, "output": str(args.output), "raw": raw,
               "noise_floor": floor, "effects": effects_used,
               "station_pose": {"reference": args.station_pose or "paper", "tracker": result.station_in_tracker_frame()}}
    if recording is not None:
        payload["recording"] = {"path": str(args.recording), "joint_samples": len(recording.joints.t),
                                "tracker_samples": len(recording.tracker.t), "clock_offset_s": recording.offset,
                                "duration_s": float(recording.joints.t[-1] - recording.joints.t[0])}

    if result.spec is not None:
        payload["session"] = dict(vars(result.spec))

    def text() -> str:
        what = f"Experiment {args.experiment}" if result.spec is None else _session_words(result.spec)
        lines = [f"{what}, seed {args.seed}: {sim_table.n} poses -> {args.output}",
                 table(METRIC_HEADERS, metrics_rows({"raw": raw, "noise floor": floor}))]
        lines.append("effects: " + "; ".join(f"{name}={_fmt_params(p)}" for name, p in effects_used.items()))
        lines.append(f"base station ({args.station_pose or 'paper'}) in the tracker's frame, as SteamVR would report "
                     f"it: --station-pose {payload['station_pose']['tracker']}")
        if recording is not None:
            r = payload["recording"]
            lines.append(f"recording -> {args.recording}: {r['duration_s']:.0f} s, {r['joint_samples']} joint states, "
                         f"{r['tracker_samples']} tracker poses, clock offset {recording.offset:+.3f} s")
        return "\n".join(lines)

    emit(args, payload, text)


def _effects(text: str | None) -> dict | None:
    """--effects as {name: theta}; a fault in it is the option's, named as such."""
    from ..effects import get_effect, parse_effects_arg
    from ..safeio import warn

    try:
        effects = parse_effects_arg(text) if text else None
    except ValueError as exc:
        raise CliError(f"--effects: {exc}") from None
    # A value no tracker shows is simulated as given, but said: degrees typed for radians,
    # millimetres for metres.
    for name, theta in (effects or {}).items():
        for words in get_effect(name).implausible(theta) if theta is not None else ():
            warn(f"--effects: {words}; simulated as given")
    return effects


# A session draws these itself (the unknown frame, the lever arm, the noise).
SESSION_DRAWS = ("station", "mount", "noise")
# --robot's word for a tracker set down by hand, which the seed would otherwise draw.
NO_ROBOT = "none"


def _simulate_session(args: argparse.Namespace, effects: dict) -> Any:
    from ..effects import get_effect
    from ..kinematics import UR_ARMS
    from ..simulate import SPREADS, simulate_session

    if args.only:
        raise CliError("--only goes with --experiment: a session draws its own frame, lever arm and noise")
    drawn = [name for name in effects if name in SESSION_DRAWS]
    if drawn:
        raise CliError(f"--session draws its own {', '.join(SESSION_DRAWS)}; --effects may add others, "
                       f"got {', '.join(drawn)}")
    if any(theta is None for theta in effects.values()):
        raise CliError("--session has no default mix to switch an effect off in: NAME=off goes with --experiment")
    if args.spread is not None and args.spread not in SPREADS:
        raise CliError(f"--spread takes {', '.join(SPREADS)}, got {args.spread!r}")
    if args.robot is not None and args.robot not in (*UR_ARMS, NO_ROBOT):
        raise CliError(f"--robot takes {', '.join(UR_ARMS)} or {NO_ROBOT} (a tracker set down by hand), "
                       f"got {args.robot!r}")
    timed = [name for name in effects if get_effect(name).needs_time]
    if timed and args.duration is None:
        raise CliError(f"{', '.join(timed)} {'acts' if len(timed) == 1 else 'act'} over the session's time, and the "
                       "session has none: give --duration SECONDS (a robot takes about 40 s a pose: 50 poses, "
                       "--duration 2000)")
    pin = {"n": args.poses, "spread": args.spread, "unremovable": None if args.unremovable is None
           else args.unremovable / 1000.0, "position_only": args.position_only,
           "robot": "" if args.robot == NO_ROBOT else args.robot, "duration": args.duration}
    return simulate_session(args.seed, extra=effects, station_pose=_station_pose(args),
                            **{k: v for k, v in pin.items() if v is not None})


def _station_pose(args: argparse.Namespace) -> str | None:
    """--station-pose for the simulator, refused before any work where it cannot place it."""
    from ..simulate import simulated_station

    try:
        simulated_station(args.station_pose)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    return args.station_pose


def _check_kind(args: argparse.Namespace) -> None:
    """An experiment or a session, and only the options of the one asked for."""
    if (args.experiment is None) == (not args.session):
        raise CliError("give either --experiment N or --session")
    given = [_spelled(args, name) for name in SESSION_OPTIONS if getattr(args, name) is not None]
    if given and not args.session:
        raise CliError(f"{', '.join(given)} {'goes' if len(given) == 1 else 'go'} with --session: an experiment's "
                       "table is the paper's protocol, its poses, orientations and times its own")
    if args.targets is not None and args.recording is None:
        raise CliError("--targets goes with --recording: it counts the poses the recording visits")


def _spelled(args: argparse.Namespace, name: str) -> str:
    option = f"--{name.replace('_', '-')}"
    return option.replace("--", "--no-", 1) if getattr(args, name) is False else option


def _session_words(spec: Any) -> str:
    parts = [f"realistic session: orientation spread {spec.spread}", f"carried by a {spec.robot}" if spec.robot else "",
             "planar" if spec.planar and not spec.robot else "",
             "position-only reference" if spec.position_only else "",
             f"unremovable error {1000 * spec.unremovable:.0f} mm" if spec.unremovable else "",
             f"{spec.duration:.0f} s long (column t)" if spec.duration else "",
             f"tracker frame {spec.offset:.1f} m away, lever arm {1000 * spec.lever:.0f} mm"]
    return "; ".join(p for p in parts if p)


def _fmt_params(params: dict[str, Any]) -> str:
    parts = []
    for key, value in params.items():
        if isinstance(value, (list, tuple)):
            parts.append(f"{key}=[{', '.join(f'{v:.4g}' for v in value)}]")
        else:
            parts.append(f"{key}={value:.4g}" if isinstance(value, float) else f"{key}={value}")
    return ", ".join(parts)


VERB = Verb(
    help="simulate a paired-pose table of paper experiment I, II or III, or a realistic robot-cell session",
    rank=1,
    outputs={"output": TABLE},
    checks_itself=("recording",),  # a file or a ROS 2 bag folder (recording.check_recording_output)
    add_arguments=add_arguments,
    run=run,
)
