"""``learner track MODEL BAG... -o STATES.csv|.npz``: the states a model tracks over bags, offline.

The reference the filter node is held to: replaying the bags through it publishes exactly
these states on ``/tpsr/state`` (msgs_doc/filter_node.md). Bags are read as the model's
training bags were (:func:`learner.inputs.read_for_model`: the model's step grid for robot
models, exact-stamp pairing for simulator models) and tracked with the model's parameters
(Algorithm 4), restarting at every gap.

``.csv``: a header line, then one row per tracked step in step order, columns
``stamp_ns,b0,...,b{r-1}`` (then ``x,y`` where the bags carry a pose, and
``cos_heading,sin_heading`` where the robot turns), every number written to round-trip
exactly (17 significant digits). ``.npz`` (no pickles): ``stamp_ns`` ``(T,)``, ``states``
``(T, r)``, ``recovered`` ``(T,)`` and, with a pose, ``positions`` ``(T, 2)`` or ``(T, 4)``.
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path
from typing import Any

import numpy as np

from learner.fit import add_topic_options
from learner.inputs import far_commands_line, read_for_model, require_given_topics
from tpsr_ros.core.episodes import track_trajectory
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.atomic import atomic_file
from tpsr_ros.io.model_io import check_output_path, open_model

__all__ = ["register", "run", "write_states"]

FORMATS = (".csv", ".npz")


def register(subparsers: Any) -> None:
    """Add the ``track`` subcommand."""
    doc = "write the states a model tracks over bags (the filter node's reference)"
    parser = subparsers.add_parser(
        "track", help=doc, description=doc[0].upper() + doc[1:] + ". " + __doc__.split("\n\n")[2]
    )
    parser.add_argument("model", type=Path, metavar="MODEL", help="model file (.npz)")
    parser.add_argument("bags", nargs="+", type=Path, metavar="BAG", help="rosbag2 MCAP bag(s)")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, metavar="STATES",
        help="states file to write: .csv or .npz",
    )  # fmt: skip
    parser.add_argument("--force", action="store_true", help="overwrite an existing STATES")
    add_topic_options(parser.add_argument_group("topics"))
    parser.set_defaults(run=run)


POSE_COLUMNS = ("x", "y", "cos_heading", "sin_heading")
"""CSV columns of the ground truth: the position, and the heading of a robot that turns."""


def write_states(
    path: Path,
    stamps: np.ndarray,
    states: np.ndarray,
    recovered: np.ndarray,
    positions: np.ndarray | None,
) -> None:
    """Write the states as ``.csv`` or ``.npz`` (module docstring), atomically."""
    if path.suffix == ".npz":
        arrays = {"stamp_ns": stamps, "states": states, "recovered": recovered}
        if positions is not None:
            arrays["positions"] = positions
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        with atomic_file(path, "wb") as handle:
            handle.write(buffer.getvalue())
        return
    columns = ["stamp_ns", *(f"b{i}" for i in range(states.shape[1]))]
    values = [states]
    if positions is not None:
        columns += list(POSE_COLUMNS[: positions.shape[1]])
        values.append(positions)
    table = np.concatenate(values, axis=1)
    with atomic_file(path, "w") as handle:
        handle.write(",".join(columns) + "\n")
        for stamp, row in zip(stamps.tolist(), table, strict=True):
            handle.write(f"{stamp}," + ",".join(format(v, ".17g") for v in row) + "\n")


def run(args: argparse.Namespace) -> int:
    """Read, track, write; say how many steps and restarts."""
    if args.output.suffix not in FORMATS:
        raise ConfigError(f"--output {str(args.output)!r}: write a .csv or .npz file")
    output = check_output_path(args.output, force=args.force)
    require_given_topics(args.bags, args)
    model_file = open_model(args.model)
    trajectory = read_for_model(model_file, args.bags, args)
    tracked = track_trajectory(model_file.model, trajectory)
    if model_file.spec is not None:  # a robot model: the filter node's far_commands
        print(f"learner track: {far_commands_line(trajectory, model_file.spec)}", file=sys.stderr)
    positions = trajectory.positions
    has_pose = positions is not None and bool(np.isfinite(positions).any())
    write_states(
        output,
        np.asarray(trajectory.stamps, dtype=np.int64),
        tracked.states,
        np.asarray(tracked.recovered, dtype=bool),
        positions if has_pose else None,
    )
    print(
        f"wrote {output}: {len(trajectory)} steps in {len(trajectory.segment_bounds())} "
        f"segment(s), {int(np.sum(tracked.recovered))} normaliser recoveries",
        file=sys.stderr,
    )
    return 0
