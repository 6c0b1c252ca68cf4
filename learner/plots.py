"""``learner plot MODEL BAG -o states.png``: the tracked states, laid out for the eye.

States come from running the model's update over the bag (guide section 4.2: tracked with
the learned parameters, not histories embedded with ``U``). The figure draws the states'
path on their two leading principal directions coloured by time (beside the true path
where the bag has a pose), the leading coordinates over time, the recoveries, and a
judgement that needs no pose: the held-out R^2 of the next images from the states against
predicting their mean (:func:`judge_states`). The command prints the judgement, the
recovery rate and, with a pose, how linearly the states predict the true position (R^2 of
an affine least-squares map).
"""

from __future__ import annotations

import argparse
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from learner.fit import add_topic_options
from learner.inputs import read_for_model, require_given_topics
from learner.adequacy import recovery_text
from tpsr_ros.core.episodes import Trajectory, track_trajectory
from tpsr_ros.core.errors import DataError
from tpsr_ros.io.model_io import check_output_path, open_model

__all__ = [
    "affine_r2",
    "loop_position_error",
    "neighbour_position_error",
    "judge_states",
    "leading_coordinates",
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


def _principal_axes(centred: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The SVD of centred states ``(T, r)`` restricted to the directions above the rounding
    level: left singular vectors ``(T, d)`` (the states whitened, up to a common factor),
    singular values ``(d,)`` and axes ``(d, r)``. Better conditioned than an
    eigendecomposition of the covariance, which squares the spread of scales."""
    left, singular, axes = np.linalg.svd(centred, full_matrices=False)
    # numpy's matrix-rank tolerance: directions below it are rounding, not data
    keep = singular > singular.max() * max(centred.shape) * np.finfo(float).eps
    if not keep.any():
        raise DataError("the states do not vary: they cannot locate anything")
    return left[:, keep], singular[keep], axes[keep]


def _location_error(
    reference: np.ndarray,
    reference_positions: np.ndarray,
    queries: np.ndarray,
    positions: np.ndarray,
    neighbours: int,
) -> float:
    """Median distance between ``positions`` and the mean position of each query's
    ``neighbours`` nearest reference states (both in the same whitened coordinates)."""
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(reference).query(queries, k=neighbours)
    located = np.asarray(reference_positions, dtype=np.float64)[nearest].mean(axis=1)
    return float(np.median(np.linalg.norm(located - np.asarray(positions), axis=1)))


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
    white, _, _ = _principal_axes(states - states.mean(axis=0))
    return _location_error(
        white[:half], positions[:half], white[half:], positions[half:], neighbours
    )


def loop_position_error(
    reference: np.ndarray,
    reference_positions: np.ndarray,
    states: np.ndarray,
    positions: np.ndarray,
    neighbours: int = NEIGHBOURS,
) -> float:
    """Median error (m) of locating the robot from the states a policy acted on.

    As :func:`neighbour_position_error`, but each of ``states`` ``(N, r)`` (the closed
    loop's) is located at the mean position of its ``neighbours`` nearest ``reference``
    states ``(T, r)`` (the random RL run's, which the planner learnt from, with their
    ``reference_positions`` ``(T, 2)``), in the reference's whitened coordinates. Set beside
    the measure on the reference alone, it tells whether the filter still knows where the
    robot is under the policy's own actions, which the random data may never have shown.
    """
    reference = np.asarray(reference, dtype=np.float64)
    states = np.asarray(states, dtype=np.float64)
    if (
        len(reference) < neighbours
        or len(reference_positions) != len(reference)
        or len(positions) != len(states)
        or len(states) == 0
        or states.shape[1:] != reference.shape[1:]
    ):
        raise DataError(
            f"need {neighbours} reference states with a position each and states of their "
            f"size with a position each, got {reference.shape} and {len(reference_positions)}, "
            f"{states.shape} and {len(positions)}"
        )
    if not (np.isfinite(reference).all() and np.isfinite(states).all()):
        raise DataError("the states hold non-finite values")
    mean = reference.mean(axis=0)
    white, singular, axes = _principal_axes(reference - mean)  # white = centred @ axes.T / s
    return _location_error(
        white, reference_positions, (states - mean) @ (axes.T / singular), positions, neighbours
    )


JUDGEMENTS = ((0.4, "good"), (0.15, "fair"), (0.0, "poor"))
"""Held-out R^2 of the next 1..10 images from the states at least this: the word for it
(below 0: worse than predicting their mean). The later images depend on actions not yet
taken, so even a model whose states give the true position to R^2 0.98 reaches only 0.50
(the sample bag ``bags/full``, the default fit)."""
DENSE_PATH = 400
"""Paths of more steps are drawn with faint lines and small dots."""
FOLDS = 5
"""Contiguous blocks of the judged steps, each predicted by a regression fitted on the rest."""
SERIES = 4
"""Leading state coordinates drawn as time series."""


@dataclass(frozen=True)
class Judgement:
    """How well the states predict the future images: held-out R^2 per horizon (``1 -``
    error / error of predicting their mean), the horizons and the scored steps."""

    per_horizon: np.ndarray
    scored: int

    @property
    def value(self) -> float:
        """R^2 averaged over the horizons."""
        return float(np.mean(self.per_horizon))

    @property
    def word(self) -> str:
        """``good``, ``fair``, ``poor`` or ``no better than the mean``."""
        return next((w for floor, w in JUDGEMENTS if self.value >= floor), "worse than the mean")

    def line(self) -> str:
        """The one-line judgement, printed and drawn."""
        k = self.per_horizon.size
        error = 100.0 * (1.0 - self.value)
        return (
            f"judgement: {self.word} - held-out R^2 {self.value:.2f} of the next 1..{k} images "
            f"from the state (prediction error {error:.0f} % of predicting their mean; "
            f"{self.scored} steps scored)"
        )


def judge_states(states: np.ndarray, trajectory: Trajectory, folds: int = FOLDS) -> Judgement:
    """Held-out R^2 of the next images' principal components from ``states`` tracked over
    ``trajectory``, no pose needed.

    The targets and the scored steps are :mod:`learner.criterion`'s (the next 1..k images'
    leading principal components, a burn-in after every restart of a segment); an affine
    ridge regression from the whitened state is fitted on all but one of ``folds``
    contiguous blocks of the scored steps and predicts the block left out, against the
    mean of the same fitted steps. Blocks rather than halves: a short log's two halves
    see different parts of the room. One regression for every next action, not one per
    action as ``learner tune`` scores: under exploration the expected future images are
    linear in a predictive state either way, and a short log cannot feed one per action.
    """
    from learner.criterion import (
        CriterionConfig,
        ObservationFeatures,
        _state_whitener,
        criterion_for,
        future_targets,
    )

    config = criterion_for(CriterionConfig(), len(trajectory))
    features = ObservationFeatures.fit(trajectory.observations, config.feature_dim)
    targets, valid = future_targets(
        features.transform(trajectory.observations), trajectory.segments, config.horizons
    )
    since_start = np.arange(len(trajectory)) - np.searchsorted(
        trajectory.segments, trajectory.segments, side="left"
    )
    rows = np.flatnonzero(valid & (since_start >= config.burn_in) & np.isfinite(states).all(1))
    if rows.size < 2 * folds:
        raise DataError(f"only {rows.size} steps can be scored: too few to judge the states")
    horizons = targets.shape[1]
    flat = targets.reshape(len(targets), -1)
    sse = np.zeros(horizons)
    sst = np.zeros(horizons)
    for block in np.array_split(rows, folds):
        fit_rows = np.setdiff1d(rows, block, assume_unique=True)
        whiten = _state_whitener(states[fit_rows], config.clip)
        design = np.column_stack([np.ones(fit_rows.size), whiten(states[fit_rows])])
        penalty = config.ridge * fit_rows.size * np.eye(design.shape[1])
        penalty[0, 0] = 0.0
        weights = np.linalg.solve(design.T @ design + penalty, design.T @ flat[fit_rows])
        test = np.column_stack([np.ones(block.size), whiten(states[block])])
        error = (flat[block] - test @ weights).reshape(block.size, horizons, -1)
        spread = (flat[block] - flat[fit_rows].mean(axis=0)).reshape(block.size, horizons, -1)
        sse += np.einsum("nkd,nkd->k", error, error)
        sst += np.einsum("nkd,nkd->k", spread, spread)
    return Judgement(1.0 - sse / sst, int(rows.size))


def leading_coordinates(states: np.ndarray, count: int = SERIES) -> tuple[np.ndarray, np.ndarray]:
    """The states on their ``count`` leading principal directions ``(T, c)`` and each
    direction's share of the variance; the directions come from the states inside the
    :func:`robust_limits` box, so a few exploded states cannot choose them."""
    finite = np.isfinite(states).all(axis=1)
    inside = finite.copy()
    for column in states.T:
        low, high = robust_limits(column)
        inside &= (column >= low) & (column <= high)
    basis = states[inside] if inside.sum() > 2 else states[finite]
    mean = basis.mean(axis=0)
    _, singular, vt = np.linalg.svd(basis - mean, full_matrices=False)
    count = min(count, vt.shape[0])
    share = singular[:count] ** 2 / max(float(np.sum(singular**2)), 1e-300)
    return np.nan_to_num(states - mean) @ vt[:count].T, share


def plot_states(
    states: np.ndarray,
    times: np.ndarray,
    positions: np.ndarray,
    recovered: np.ndarray,
    output: Path,
    *,
    judgement: Judgement | None = None,
    title: str = "",
    notes: Sequence[str] = (),
) -> None:
    """Draw the tracked states for the eye and write a PNG.

    Top left, the path of the states on their two leading principal directions coloured
    by time; top middle (with a pose), the true path in the same colours; top right, the
    judgement (held-out R^2 of the future images per horizon against predicting their
    mean); below, the leading coordinates over time. Recoveries are marked in every panel;
    states beyond the axes (:func:`robust_limits`) are drawn on the edge as open
    triangles, counted and explained in the legend. ``notes`` are wrapped into the footer.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    coords, share = leading_coordinates(states)
    if coords.shape[1] < 2:  # one state dimension: against time
        coords = np.column_stack([times, coords[:, 0]])
        share = np.concatenate([[np.nan], share])
    has_pose = bool(np.isfinite(positions[:, :2]).all(axis=1).sum() > 1)
    top = 3 if has_pose else 2
    series = min(SERIES, coords.shape[1]) if np.isfinite(share[0]) else 1
    fig = plt.figure(figsize=(14, 12))
    outer = fig.add_gridspec(
        3, 1, height_ratios=[5.5, 1.1, 1.3 * series], hspace=0.3,
        left=0.06, right=0.97, top=0.93, bottom=0.15,
    )  # fmt: skip
    upper = outer[0].subgridspec(1, top, wspace=0.28)
    middle = outer[1].subgridspec(2, 1, height_ratios=[1, 1.2], hspace=0.2)
    lower = outer[2].subgridspec(series, 1, hspace=0.15)
    colour = plt.get_cmap("viridis")
    span = (float(times.min()), float(times.max()) if times.max() > times.min() else 1.0)
    norm = plt.Normalize(*span)

    def path(ax: Any, xy: np.ndarray, label_x: str, label_y: str) -> int:
        (x0, x1), (y0, y1) = robust_limits(xy[:, 0]), robust_limits(xy[:, 1])
        outside = (xy[:, 0] < x0) | (xy[:, 0] > x1) | (xy[:, 1] < y0) | (xy[:, 1] > y1)
        drawn = np.column_stack([np.clip(xy[:, 0], x0, x1), np.clip(xy[:, 1], y0, y1)])
        segments = np.stack([drawn[:-1], drawn[1:]], axis=1)
        dense = len(xy) > DENSE_PATH  # a long run: faint lines, small dots
        lines = LineCollection(segments, cmap=colour, norm=norm, linewidths=0.5 if dense else 1.2,
                               alpha=0.15 if dense else 0.8)  # fmt: skip
        lines.set_array(times[1:])
        ax.add_collection(lines)
        ax.scatter(*drawn[~outside].T, c=times[~outside], cmap=colour, norm=norm,
                   s=3 if dense else 10, zorder=3, linewidths=0)  # fmt: skip
        if outside.any():
            ax.scatter(*drawn[outside].T, facecolors="none", edgecolors="black", marker="^",
                       s=40, zorder=4)  # fmt: skip
        ax.scatter(*drawn[recovered].T, c="red", marker="x", s=45, linewidths=1.5, zorder=5)
        ax.scatter(*drawn[:1].T, facecolors="none", edgecolors="black", s=120, zorder=5)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_xlabel(label_x)
        ax.set_ylabel(label_y)
        return int(outside.sum())

    ax = fig.add_subplot(upper[0, 0])
    beyond = path(
        ax, coords[:, :2], f"state direction 1 ({share[0]:.0%} of the variance)"
        if np.isfinite(share[0]) else "time (s)", f"state direction 2 ({share[1]:.0%})"
        if np.isfinite(share[0]) else "state",
    )  # fmt: skip
    ax.set_title("the states' path (two leading directions)", fontsize=11)
    if has_pose:
        ax = fig.add_subplot(upper[0, 1])
        path(ax, positions[:, :2], "true x (m)", "true y (m)")
        ax.set_title("the true path, same colours (not a learning input)", fontsize=11)
    ax = fig.add_subplot(upper[0, top - 1])
    if judgement is not None:
        k = np.arange(1, judgement.per_horizon.size + 1)
        bars = np.clip(judgement.per_horizon, -1.0, 1.0)
        ax.bar(k, bars, color=["tab:green" if v > 0 else "tab:red" for v in bars])
        ax.axhline(0.0, color="black", linewidth=1)
        ax.set_ylim(min(-0.2, float(bars.min()) - 0.05), 1.0)
        ax.set_xlabel("images ahead")
        ax.set_ylabel("held-out R^2 (0 = predicting the mean)")
        ax.set_title(f"predicting the future images:\n{judgement.word}", fontsize=11)
        ax.text(0.97, 0.95, f"R^2 {judgement.value:.2f} over 1..{k.size} images ahead"
                + (" (bars clipped at -1)" if judgement.per_horizon.min() < -1 else ""),
                transform=ax.transAxes, ha="right", va="top", fontsize=9)  # fmt: skip
    else:
        ax.axis("off")
    colour_bar = fig.add_subplot(middle[1].subgridspec(1, 4)[0, 1:3])
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=colour), cax=colour_bar,
                 orientation="horizontal", label="time (s) - the colour of every path")  # fmt: skip
    legend = fig.add_subplot(middle[0])
    legend.axis("off")
    handles = [
        Line2D([], [], marker="o", linestyle="", markerfacecolor="none", markeredgecolor="black",
               markersize=10, label="first step"),
        Line2D([], [], marker="x", linestyle="", color="red", markersize=8,
               label=f"recovery ({int(recovered.sum())}): the state restarted from b_*"),
        Line2D([], [], marker="^", linestyle="", markerfacecolor="none", markeredgecolor="black",
               markersize=8, label=f"{beyond} state(s) beyond the axes, drawn on the edge "
               f"(axes cover {1 - 2 * AXIS_QUANTILE:.0%} of each coordinate)"),
    ]  # fmt: skip
    legend.legend(handles=handles, loc="center", ncol=3, frameon=False, fontsize=10)
    for row in range(series):
        ax = fig.add_subplot(lower[row])
        values = coords[:, row] if np.isfinite(share[0]) else coords[:, 1]
        low, high = robust_limits(values)
        ax.plot(times, np.clip(values, low, high), color="tab:blue", linewidth=1)
        for when in times[recovered]:
            ax.axvline(when, color="red", linewidth=0.8, alpha=0.6)
        ax.set_ylim(low, high)
        ax.set_xlim(*span)
        ax.set_ylabel(f"direction {row + 1}", fontsize=9)
        ax.tick_params(labelsize=8)
        if row < series - 1:
            ax.tick_params(labelbottom=False)
        else:
            ax.set_xlabel("time (s); red lines: recoveries")
    if title:
        fig.suptitle(title, fontsize=13)
    wrapped = "\n".join(textwrap.fill(line, 175) for line in notes)
    fig.text(0.02, 0.012, wrapped, fontsize=9, ha="left", va="bottom")
    if judgement is not None:
        lines = wrapped.count("\n") + 1
        fig.text(0.02, 0.02 + 0.0125 * lines, textwrap.fill(judgement.line(), 150),
                 fontsize=10.5, fontweight="bold", ha="left", va="bottom")  # fmt: skip
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
    fit_line = "" if r2 is None else f"; R^2 of the true {_r2_text(r2, ', ')} from the states"
    try:
        judgement: Judgement | None = judge_states(tracked.states, trajectory)
    except DataError as exc:
        judgement, why = None, str(exc).splitlines()[0]
    restarts = recovery_text(int(tracked.recovered.sum()), len(trajectory))
    training = model_file.training.get("adequacy")
    trained = (
        f"; over its training data it restarts at {training.get('recoveries')} of "
        f"{training.get('tracked_steps')} steps"
        if isinstance(training, dict) else ""
    )
    notes = [
        f"tracking {restarts} (recovery rate {tracked.recovered.mean():.2f}){trained}. "
        + RECOVERY,
        "the judgement needs no pose: it is how much better than their mean the states "
        "predict the next 1..10 images (good from 0.4, fair from 0.15; the later images "
        "depend on actions not yet taken, so a model that locates the robot to R^2 0.98 "
        "reaches 0.5); near 0 or below, the states carry nothing the images' average does "
        "not. When this bag trained the model, the fit saw its steps: a fresh recording is "
        "the fairer test.",
    ]
    stamps = np.asarray(trajectory.stamps, dtype=np.float64)
    times = (stamps - stamps[0]) * 1e-9 if stamps.size else stamps
    plot_states(
        tracked.states,
        times,
        trajectory.positions,
        np.asarray(tracked.recovered, dtype=bool),
        output,
        judgement=judgement,
        title=f"{model.method} states over {len(trajectory)} steps ({times[-1]:.0f} s), state "
        f"dimension {model.state_dim}{fit_line}",
        notes=notes,
    )
    print(
        f"wrote {output}: {len(trajectory)} steps; tracking {restarts} (recovery rate "
        f"{tracked.recovered.mean():.2f}: steps whose predicted observation probability was "
        f"not positive, restarted from b_*){trained}"
    )
    print(judgement.line() if judgement is not None else f"judgement: none ({why})")
    if r2 is None:
        print("no ground-truth pose in the bag(s): states coloured by time, no R^2 of the position")
    else:
        partial = "" if known.all() else f" (over the {int(known.sum())} steps with a pose)"
        what = "true pose" if r2.size > 2 else "true position"
        print(f"R^2 of {what} from states (affine least squares): {_r2_text(r2)}{partial}")
    return 0
