"""``learner plot MODEL BAG -o states.png``: tracked states coloured by ground truth.

States come from running the model's update over the bag (guide section 4.2: tracked with
the learned parameters, not histories embedded with ``U``). The figure scatters pairs of
the first state dimensions, one row per pair, coloured by reward, true x and true y, like
the guide's figure 4.5 (a-c). The command also prints how linearly the states predict the
true position (R^2 of an affine least-squares map), a one-number check of the topology.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from typing import Any

import numpy as np

from learner.fit import add_topic_options
from learner.inputs import read_for_model, require_given_topics
from tpsr_ros.core.episodes import track_trajectory
from tpsr_ros.core.errors import DataError
from tpsr_ros.io.model_io import check_output_path, open_model

__all__ = [
    "affine_r2",
    "neighbour_position_error",
    "plot_states",
    "register",
    "robust_limits",
    "run",
]

NEIGHBOURS = 10
"""States whose positions are averaged by :func:`neighbour_position_error`."""
AXIS_QUANTILE = 0.005
"""Axes span the states between this quantile and its complement (padded); states beyond
are drawn on the edge and counted, so a few outliers cannot squash the rest into a dot."""
RECOVERY = (
    "recovery: a step whose predicted observation probability was not positive, so the "
    "state restarted from b_* (the normaliser guard of the state update, guide 3.3)"
)


def robust_limits(values: np.ndarray) -> tuple[float, float]:
    """Axis limits covering the values between the :data:`AXIS_QUANTILE` quantiles, padded."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return -1.0, 1.0
    low, high = np.quantile(finite, [AXIS_QUANTILE, 1 - AXIS_QUANTILE])
    pad = 0.05 * (high - low) if high > low else max(abs(float(low)), 1.0) * 0.05
    return float(low - pad), float(high + pad)


def affine_r2(states: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """R^2 per target column of the least-squares affine map ``states (T, r) -> targets (T, c)``."""
    states = np.asarray(states, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.float64).reshape(states.shape[0], -1)
    design = np.concatenate([states, np.ones((states.shape[0], 1))], axis=1)
    coef, *_ = np.linalg.lstsq(design, targets, rcond=None)
    residual = ((targets - design @ coef) ** 2).sum(axis=0)
    total = ((targets - targets.mean(axis=0)) ** 2).sum(axis=0)
    return np.asarray(1.0 - residual / total)


POSE_NAMES = ("x", "y", "cos heading", "sin heading")
"""The ground truth's columns: the position, and for a robot that turns, its heading."""


def _r2_text(r2: np.ndarray, separator: str = ", ") -> str:
    """``x 0.912, y 0.874[, cos heading ..., sin heading ...]``."""
    pairs = zip(POSE_NAMES, r2, strict=False)
    return separator.join(f"{name} {value:.3f}" for name, value in pairs)


def neighbour_position_error(
    states: np.ndarray, positions: np.ndarray, neighbours: int = NEIGHBOURS
) -> float:
    """Median error (in position units) of locating the robot from its state, nonlinearly.

    The states ``(T, r)`` are whitened with their own covariance (directions below the
    rounding level dropped), so the measure is blind to invertible linear maps of the
    states, as fitted Q with ``state_scaling=whiten`` is. Each state of the second
    half is located at the mean position of its ``neighbours`` nearest states of the first
    half; the result is the median distance to its true position ``(T, 2)``. Unlike the
    affine R^2 it credits any smooth map from states to positions and reports the local
    precision a planner can use near walls, not the global linear fit; where distant places
    look alike (aliasing) the upper quantiles grow, not the median.
    """
    from scipy.spatial import cKDTree

    states = np.asarray(states, dtype=np.float64)
    positions = np.asarray(positions, dtype=np.float64)
    half = len(states) // 2
    if half < neighbours or len(positions) != len(states):
        raise DataError(
            f"need {2 * neighbours} states with a position each, got {len(states)} states "
            f"and {len(positions)} positions"
        )
    if not np.isfinite(states).all():
        raise DataError("the states hold non-finite values")
    centred = states - states.mean(axis=0)
    # whitened = the left singular vectors (up to a common factor): better conditioned than
    # an eigendecomposition of the covariance, which squares the spread of scales
    left, singular, _ = np.linalg.svd(centred, full_matrices=False)
    # numpy's matrix-rank tolerance: directions below it are rounding, not data
    keep = singular > singular.max() * max(centred.shape) * np.finfo(float).eps
    if not keep.any():
        raise DataError("the states do not vary: they cannot locate anything")
    white = left[:, keep]
    _, nearest = cKDTree(white[:half]).query(white[half:], k=neighbours)
    located = positions[:half][nearest].mean(axis=1)
    return float(np.median(np.linalg.norm(located - positions[half:], axis=1)))


def plot_states(
    states: np.ndarray,
    positions: np.ndarray,
    rewards: np.ndarray,
    output: Path,
    *,
    max_pairs: int = 3,
    title: str = "",
    footnote: str = "",
) -> None:
    """Scatter dimension pairs of ``states (T, r)`` coloured by reward, x and y; write a PNG.

    Colourings without data (no reward, no ground truth) are left out; with neither, the
    states are coloured by time (step number). Axes follow :func:`robust_limits`: states
    beyond them are drawn on the edge as crosses and counted in the panel's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    r = states.shape[1]
    if r >= 2:
        pairs = list(itertools.combinations(range(min(r, 3)), 2))[:max_pairs]
    else:
        pairs = [(-1, 0)]  # the single dimension against the step index
    finite = np.isfinite(rewards)
    low = min(float(np.nanmin(rewards)) if finite.any() else -1.0, -1e-9)
    high = max(float(np.nanmax(rewards)) if finite.any() else 1.0, 1e-9)
    steps = np.arange(states.shape[0])
    colourings = [
        ("reward", rewards, TwoSlopeNorm(vmin=low, vcenter=0.0, vmax=high)),
        ("true x", positions[:, 0], None),
        ("true y", positions[:, 1], None),
    ]
    colourings = [c for c in colourings if np.isfinite(c[1]).any()] or [("time", steps, None)]
    fig, axes = plt.subplots(
        len(pairs), len(colourings), figsize=(4 * len(colourings), 4 * len(pairs)), squeeze=False
    )
    for row, (i, j) in enumerate(pairs):
        xs = steps.astype(np.float64) if i < 0 else states[:, i]
        (x0, x1), (y0, y1) = robust_limits(xs), robust_limits(states[:, j])
        outside = (xs < x0) | (xs > x1) | (states[:, j] < y0) | (states[:, j] > y1)
        x_drawn, y_drawn = np.clip(xs, x0, x1), np.clip(states[:, j], y0, y1)
        for col, (name, colour, norm) in enumerate(colourings):
            ax = axes[row, col]
            sc = ax.scatter(
                x_drawn[~outside], y_drawn[~outside], c=colour[~outside], s=2, cmap="coolwarm",
                norm=norm, rasterized=True, linewidths=0,
            )  # fmt: skip
            if outside.any():
                ax.scatter(
                    x_drawn[outside], y_drawn[outside], c="black", s=8, marker="x",
                    linewidths=0.6, rasterized=True,
                )  # fmt: skip
            ax.set_xlim(x0, x1)
            ax.set_ylim(y0, y1)
            ax.ticklabel_format(style="sci", scilimits=(-3, 4), useOffset=False)
            ax.set_xlabel("step" if i < 0 else f"state dim {i}")
            ax.set_ylabel(f"state dim {j}")
            count = int(outside.sum())
            beyond = f"\n{count} outlying states on the edge (x)" if count else ""
            ax.set_title(f"coloured by {name}{beyond}", fontsize=10)
            fig.colorbar(sc, ax=ax, shrink=0.8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    if footnote:
        fig.subplots_adjust(bottom=fig.subplotpars.bottom + 0.25 / (4 * len(pairs)))
        fig.text(0.01, 0.005, footnote, fontsize=8, ha="left", va="bottom")
    fig.savefig(output, dpi=80)
    plt.close(fig)


def register(subparsers: Any) -> None:
    """Add the ``plot`` subcommand."""
    doc = "plot states tracked over a bag, coloured by reward and true position (guide fig. 4.5)"
    parser = subparsers.add_parser("plot", help=doc, description=doc[0].upper() + doc[1:] + ".")
    parser.add_argument("model", type=Path, metavar="MODEL", help="model file (.npz)")
    parser.add_argument(
        "bags",
        type=Path,
        nargs="+",
        metavar="BAG",
        help="bag(s) with images and actions (and ground-truth pose and reward, if any)",
    )
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="PNG")
    parser.add_argument("--force", action="store_true", help="overwrite an existing PNG")
    add_topic_options(parser.add_argument_group("topics"))
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Track, plot, and print the R^2 of true position from the states."""
    output = Path(args.output)
    if output.exists() and not args.force:
        raise DataError(f"output file {str(output)!r} already exists; use --force to overwrite it")
    check_output_path(output, force=True)
    require_given_topics(args.bags, args)
    model_file = open_model(args.model)
    model = model_file.model
    # simulator models demand ground truth as always; robot models plot without it
    exact = model_file.spec is None
    trajectory = read_for_model(model_file, args.bags, args, require_ground_truth=exact)
    tracked = track_trajectory(model, trajectory)
    known = np.isfinite(trajectory.positions).all(axis=1)
    r2 = affine_r2(tracked.states[known], trajectory.positions[known]) if known.sum() > 2 else None
    fit_line = "" if r2 is None else f" (R^2 of {_r2_text(r2, ', ')} from an affine map)"
    plot_states(
        tracked.states,
        trajectory.positions,
        trajectory.rewards,
        output,
        title=f"{model.method} states over {len(trajectory)} steps{fit_line}",
        footnote=f"{int(tracked.recovered.sum())} recoveries; {RECOVERY}",
    )
    print(
        f"wrote {output}: {len(trajectory)} steps, {int(tracked.recovered.sum())} recoveries "
        "(steps whose predicted observation probability was not positive: restarted from b_*)"
    )
    if r2 is None:
        print("no ground-truth pose in the bag(s): states coloured by time, no R^2")
    else:
        partial = "" if known.all() else f" (over the {int(known.sum())} steps with a pose)"
        what = "true pose" if r2.size > 2 else "true position"
        print(f"R^2 of {what} from states (affine least squares): {_r2_text(r2)}{partial}")
    return 0
