"""``learner info MODEL``: what a model file holds (method, parameters, data, fit summary)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from tpsr_ros.io.model_io import load_model, model_stream_spec, read_metadata

__all__ = ["info_lines", "register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``info`` subcommand."""
    doc = "print the metadata and fit summary of a model file"
    parser = subparsers.add_parser("info", help=doc, description=doc[0].upper() + doc[1:] + ".")
    parser.add_argument("model", type=Path, metavar="MODEL", help="model file (.npz)")
    parser.add_argument("--json", action="store_true", help="print the raw JSON metadata")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Validate the whole file (arrays too), then print its metadata."""
    load_model(args.model)
    metadata = read_metadata(args.model)
    if args.json:
        print(json.dumps(metadata, indent=2, sort_keys=True))
    else:
        print("\n".join(info_lines(args.model, metadata)))
    return 0


def _short(values: Any) -> str:
    if isinstance(values, list):
        return " ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in values)
    return str(values)


def info_lines(path: Path, metadata: dict[str, Any]) -> list[str]:
    """Human-readable description of a model's metadata."""
    summary = metadata.get("summary", {})
    training = metadata.get("training", {})
    lines = [
        f"model: {path}",
        f"format: {metadata['format']} version {metadata['format_version']}, created "
        f"{metadata.get('created')}, tpsr_ros {metadata.get('software', {}).get('tpsr_ros')}",
        f"method: {metadata['method']}, state dimension {metadata.get('state_dim')}, "
        f"{metadata['n_actions']} actions, observation size "
        f"{metadata.get('observation', {}).get('size')}",
        "parameters: " + ", ".join(f"{k}={v}" for k, v in metadata["parameters"].items()),
    ]
    if training:
        bags = [b.get("path") for b in training.get("bags", [])]
        lines.append(
            f"training data: {training.get('steps')} steps, {training.get('segments')} "
            f"segment(s), {training.get('episodes')} episodes, environment "
            f"{training.get('environment')}, stamps {training.get('stamps_ns')} ns"
        )
        lines.append(f"bags: {', '.join(map(str, bags))}")
    spec = model_stream_spec(path, metadata)
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
    for key, ev in summary.get("explained_variance", {}).items():
        lines.append(f"explained variance ({key}): {ev['total']:.3f}")
    if "timings" in summary:
        lines.append(
            "fit timing: " + "; ".join(f"{k} {v:.3f} s" for k, v in summary["timings"].items())
        )
    return lines
