"""``learner closed-loop POLICY --environment E``: the command line of the closed loop
(:mod:`learner.closed_loop`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from learner.closed_loop import format_trial, run_closed_loop
from learner.evaluate import EVALUATION_SEED, Trial, add_camera_size_option
from sim_node import Environment
from sim_node.options import add_vertical_half_extent_option
from tpsr_ros.core.errors import ModelFormatError

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``closed-loop`` subcommand."""
    doc = (
        "score a policy with the standard protocol over the nodes: sim_node and the filter "
        "node as separate processes in lockstep over ROS 2 (rclpy or the DDS backend)"
    )
    parser = subparsers.add_parser(
        "closed-loop",
        help=doc,
        description=doc[0].upper() + doc[1:] + ". Prints each trial, then `score: X`, "
        "exactly as `learner evaluate` does for the same policy.",
    )
    parser.add_argument("policy", type=Path, metavar="POLICY")
    parser.add_argument("--environment", required=True, choices=[e.value for e in Environment])
    add_vertical_half_extent_option(parser, "sim_node's camera (the model's must match)")
    add_camera_size_option(parser)
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        metavar="MODEL",
        help="the policy's model file (default: the path recorded in the policy)",
    )
    parser.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="BAG",
        help="also record every topic of the run into a new bag",
    )
    parser.add_argument(
        "--logs",
        type=Path,
        default=None,
        metavar="DIR",
        help="keep the nodes' logs in DIR (default: only when a run fails)",
    )
    parser.add_argument(
        "--seed", type=int, default=EVALUATION_SEED, help="simulator seed (default: %(default)s)"
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=60.0,
        metavar="S",
        help="longest wait for any one stage (default: %(default)s s)",
    )
    parser.add_argument(
        "--domain-id",
        type=int,
        default=None,
        metavar="N",
        help="ROS_DOMAIN_ID to use (default: a free one in 1..101 at random)",
    )
    parser.add_argument(
        "--transport",
        choices=("rclpy", "dds"),
        default=None,
        help="middleware of the nodes (default: TPSR_TRANSPORT, else rclpy if importable, "
        "else dds)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the closed loop; print each trial, then ``score: <mean>`` as the last line."""
    if args.seed < 0:
        raise ModelFormatError(f"--seed must be >= 0, got {args.seed}")

    def show(index: int, trial: Trial) -> None:
        print(format_trial(index, trial), flush=True)

    result = run_closed_loop(
        args.policy,
        args.environment,
        vertical_half_extent=args.vertical_half_extent,
        model_path=args.model,
        record=args.record,
        log_dir=args.logs,
        seed=args.seed,
        timeout_s=args.timeout,
        domain_id=args.domain_id,
        transport=args.transport,
        camera_size=args.camera_size,
        on_trial=show,
        say=lambda text: print(f"learner closed-loop: {text}", file=sys.stderr, flush=True),
    )
    print(f"score: {result.evaluation.score:.1f}")
    return 0
