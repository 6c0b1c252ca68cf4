"""``learner info MODEL``: what a model file holds (method, preset, parameters, data, summary)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from learner.adequacy import MAX_RECOVERY_RATE, MIN_EPISODES_PER_ACTION
from learner.inputs import environment_label
from tpsr_ros.io.model_io import metadata_field, open_model
from tpsr_ros.io.stream_spec import StreamSpec

__all__ = ["info_lines", "predicted_images", "register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``info`` subcommand."""
    doc = "print the metadata and fit summary of a model file"
    parser = subparsers.add_parser("info", help=doc, description=doc[0].upper() + doc[1:] + ".")
    parser.add_argument("model", type=Path, metavar="MODEL", help="model file (.npz)")
    parser.add_argument("--json", action="store_true", help="print the raw JSON metadata")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Validate the whole file (arrays too), then print its metadata."""
    model_file = open_model(args.model)
    if args.json:
        print(json.dumps(model_file.metadata, indent=2, sort_keys=True))
    else:
        print("\n".join(info_lines(model_file.path, model_file.metadata, model_file.spec)))
    return 0


def _short(values: Any) -> str:
    if isinstance(values, list):
        return " ".join(_num(v, ".4g") for v in values)
    return str(values)


def _num(value: Any, spec: str) -> str:
    """``value`` formatted with ``spec`` when it is a number, else as text."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return format(value, spec)
    return str(value)


def _mapping(value: Any) -> dict[str, Any]:
    return value if isinstance(value, dict) else {}


def _preset_line(record: Any) -> str:
    """``preset: best (its turning robot's settings); changed by options: rank=5`` (models
    written before presets: unknown)."""
    record = _mapping(record)
    name = record.get("name")
    if not isinstance(name, str):
        return "preset: not recorded (a model written before presets existed)"
    changed = _mapping(record.get("changed"))
    what = ", ".join(f"{k}={v}" for k, v in changed.items()) or "nothing"
    turning = " (its turning robot's settings)" if record.get("turning") is True else ""
    return f"preset: {name}{turning}; changed by options: {what}"


def _camera(training: dict[str, Any]) -> str:
    """`` (camera vertical half-extent T)`` when the training bags record the simulated
    camera's (``sim_node.generate``), else nothing."""
    value = training.get("vertical_half_extent")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return ""
    return f" (camera vertical half-extent {value:g})"


def _adequacy_line(adequacy: dict[str, Any]) -> str:
    """``recovery rate 0.06 (tracking the training data restarts at 5 of 83 steps);
    13.5 training episodes per action`` and, for too little data, a warning."""
    line = (
        f"recovery rate {_num(adequacy.get('recovery_rate'), '.2f')} (tracking the training "
        f"data restarts at {adequacy.get('recoveries')} of {adequacy.get('tracked_steps')} "
        f"steps); {_num(adequacy.get('episodes_per_action'), '.1f')} training episodes per "
        "action"
    )
    if adequacy.get("too_little") is True:
        line += (
            " - too little data for a good model (wanted: at least "
            f"{MIN_EPISODES_PER_ACTION} episodes per action, at most "
            f"{MAX_RECOVERY_RATE:.0%} of the steps restarting)"
        )
    return line


def info_lines(
    path: Path, metadata: dict[str, Any], spec: StreamSpec | None = None
) -> list[str]:
    """Human-readable description of a model's metadata (``spec``: its input streams)."""
    summary = _mapping(metadata.get("summary"))
    training = _mapping(metadata.get("training"))
    lines = [
        f"model: {path}",
        f"format: {metadata['format']} version {metadata['format_version']}, created "
        f"{metadata.get('created')}, tpsr_ros {metadata_field(metadata, 'software', 'tpsr_ros')}",
        f"method: {metadata['method']}, state dimension {metadata.get('state_dim')}, "
        f"{metadata['n_actions']} actions, observation size "
        f"{metadata_field(metadata, 'observation', 'size')}",
        _preset_line(metadata.get("preset")),
        "parameters: " + ", ".join(f"{k}={v}" for k, v in metadata["parameters"].items()),
    ]
    if training:
        bags = training.get("bags")
        paths = [metadata_field(b, "path") for b in bags] if isinstance(bags, list) else []
        lines.append(
            f"training data: {training.get('steps')} steps, {training.get('segments')} "
            f"segment(s), {training.get('episodes')} episodes, "
            f"{environment_label(training.get('environment'))}{_camera(training)}, stamps "
            f"{training.get('stamps_ns')} ns"
        )
        lines.append(f"bags: {', '.join(map(str, paths))}")
        if adequacy := _mapping(training.get("adequacy")):
            lines.append(_adequacy_line(adequacy))
    if spec is not None:
        prep, grid = spec.preprocessing, spec.grid.as_dict()
        book = spec.codebook
        lines.append(
            f"input: camera {spec.image_topic} ({spec.image_type}) as {prep.width}x"
            f"{prep.height} {'grey' if prep.grey else 'colour'}; commands {spec.action_topic} "
            f"({spec.action_type}) as {len(book)} {book.kind} actions over "
            f"{', '.join(book.components)}; steps of {grid['step_period_s']:g} s (image "
            f"timeout {grid['image_timeout_s']:g} s, command timeout "
            f"{grid['command_timeout_s']:g} s)"
        )
    if "singular_values" in summary:
        lines.append(f"singular values of P_TH: {_short(summary['singular_values'])}")
    for key, ev in _mapping(summary.get("explained_variance")).items():
        lines.append(f"explained variance ({key}): {_num(metadata_field(ev, 'total'), '.3f')}")
    if "timings" in summary:
        timings = _mapping(summary["timings"])
        lines.append(
            "fit timing: " + "; ".join(f"{k} {_num(v, '.3f')} s" for k, v in timings.items())
        )
    if kernel := _mapping(summary.get("obs_kernel")):
        centres = metadata_field(metadata, "parameters", "obs_centers")
        lines.append(kernel_line(kernel, centres))
    if refined := _mapping(summary.get("refinement")):
        lines.append(
            f"refinement: {_num(refined.get('iterations'), 'd')} iteration(s), best "
            f"{_num(refined.get('best_iteration'), 'd')} (0: the spectral model kept); "
            f"held-out unexplained variance of {predicted_images(refined)} "
            f"{_num(refined.get('heldout_unexplained_spectral'), '.4f')} -> "
            f"{_num(refined.get('heldout_unexplained'), '.4f')}"
        )
    return lines


def kernel_line(kernel: dict[str, Any], n_centres: int) -> str:
    """The observation kernel a fit used (its ``fit_info["obs_kernel"]``): the width, and
    how many of the centres an image's weights spread over (:mod:`tpsr_ros.core.kernel_width`)."""
    given = kernel.get("sigma_given")
    widened = f" (widened from {_num(given, 'g')})" if given is not None else ""
    return (
        f"observation kernel: sigma^O {_num(kernel.get('sigma'), 'g')}{widened}; an image's "
        f"weights spread over a median {_num(kernel.get('effective_centres'), '.2f')} "
        f"effective centres of {n_centres}"
    )


def predicted_images(refined: dict[str, Any]) -> str:
    """What a refinement's states were fitted to predict (its ``fit_info`` entry): the
    next images, and the last ones too with a past target (``tpsr.refine_past``)."""
    past = refined.get("past", 0)
    valid = isinstance(past, int) and not isinstance(past, bool) and past > 0
    return "the next images" + (f" and the last {past}" if valid else "")
