"""`posecorr ros2`."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import options
from .common import CliError, Verb, allow_arguments, allow_options, print_json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="the model (ONNX)")
    p.add_argument("--input", default="/tracker/pose", help="PoseStamped topic of the raw tracker pose")
    p.add_argument("--output", default="/tracker/pose_corrected", help="topic of the corrected pose")
    p.add_argument("--node-name", default="posecorr", metavar="NAME",
                   help="the node's name (its parameters at /NAME, its diagnostics named so): one per "
                        "tracker where several run on one ROS domain")
    p.add_argument("--frame", default="base_link",
                   help="frame id of the corrected pose (the robot's, where the model's reference poses were)")
    p.add_argument("--input-frame", metavar="FRAME",
                   help="the frame id of the raw poses the model was fitted in: a pose in any other "
                        "is refused (default: every frame taken, each one logged once)")
    p.add_argument("--registration", default="paper", type=_registration, metavar="TRANSFORM",
                   help="base_T_(tracker frame) that mapped the model's measured poses, as `ingest "
                        "--registration` took it (paper, none, or x,y,z,qw,qx,qy,qz): each pose is mapped "
                        "so before the model (default: paper, ingest's default; none: the poses as published)")
    p.add_argument("--reliable", action="store_true", help="reliable QoS (default: sensor data, best effort)")
    p.add_argument("--t0", type=options.real(),
                   help="models with time: t = stamp - T0 (default: the first pose's stamp)")
    p.add_argument("--diagnostics-period", type=options.real(0, 3600, open_lo=True), default=1.0,
                   help="seconds between /diagnostics messages")
    allow_options(p)


def _registration(text: str):
    """None for none (no work a pose), else the 4x4 transform."""
    from ..geometry import parse_transform

    return None if text.strip().lower() == "none" else parse_transform(text, "registration", argparse.ArgumentTypeError)


def run(args: argparse.Namespace) -> None:
    """Serves until a signal; the summary is printed, then the exit status is the
    signal's convention (SIGTERM 143, SIGINT 130), as for every verb."""
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.validate_full_topic_name import validate_full_topic_name
    from rclpy.validate_node_name import validate_node_name
    from rclpy.validate_topic_name import validate_topic_name

    from ..ros2.node import run_node
    from ..safeio import Terminated

    try:
        validate_node_name(args.node_name)
    except Exception as exc:   # rclpy's InvalidNodeNameException, its first line the reason
        raise CliError(f"--node-name {args.node_name!r}: {str(exc).splitlines()[0]}") from None
    for option, name in (("--input", args.input), ("--output", args.output)):
        try:   # as the node resolves it (its name, the root namespace): '//' shows only then
            validate_topic_name(name)
            validate_full_topic_name(expand_topic_name(name, args.node_name, "/"))
        except Exception as exc:   # rclpy's InvalidTopicNameException, its first line the reason
            raise CliError(f"{option} {name!r}: {str(exc).splitlines()[0]}") from None
    final = run_node(args.model, node_name=args.node_name, input_topic=args.input, output_topic=args.output,
                     frame=args.frame, input_frame=args.input_frame, registration=args.registration,
                     reliable=args.reliable, t0=args.t0,
                     diag_period=args.diagnostics_period, allow=allow_arguments(args),
                     log=(lambda m: print(m, file=sys.stderr, flush=True)))
    if args.json:
        print_json(final)
    else:
        # no pose published has no latency (a publisher whose QoS the node's cannot take, say)
        latency = (f"p50 {final['latency_p50_us']} us, p99 {final['latency_p99_us']} us"
                   if final["poses_out"] != "0" else "no poses")
        print(f"stopped: {final['poses_in']} poses in, {final['poses_out']} out, "
              f"{final['refused']} refused"
              + (f", {final['beyond_training_orientations']} beyond the orientations the model was fitted on"
                 if final.get("beyond_training_orientations", "0") != "0" else "")
              + f"; per model generation {final['poses_per_generation']}; "
              f"added latency {latency}")
    sys.stdout.flush()
    if final["stopped_by"] == "SIGTERM":
        raise Terminated()
    if final["stopped_by"] == "SIGINT":
        raise KeyboardInterrupt()


VERB = Verb(
    help="a ROS 2 node: correct a PoseStamped topic live, swap models while it runs",
    rank=11,
    needs="ros2",
    models=("model",),
    add_arguments=add_arguments,
    run=run,
)
