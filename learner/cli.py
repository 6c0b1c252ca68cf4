"""``python -m learner COMMAND ...``: one parser, one subcommand per module.

Each module named in :data:`SUBCOMMANDS` adds its own subcommand: it exposes
``register(subparsers)``, which calls ``subparsers.add_parser(...)`` and sets ``run`` with
``parser.set_defaults(run=function)``; ``function(args) -> int`` does the work. A module
that only has ``main(argv) -> int`` (its own argparse) is mounted as a pass-through
subcommand. Adding a command = adding a module and its name here.

Errors: a :class:`~tpsr_ros.core.errors.TpsrError` prints one line ``learner: error: ...`` and
exits 1; bad usage prints ``learner COMMAND: error: ...`` and exits 2; no tracebacks.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Any

from tpsr_ros.cli import ArgumentParser, run_cli

__all__ = ["PROG", "SUBCOMMANDS", "build_parser", "entry", "main"]

PROG = "learner"
SUBCOMMANDS: dict[str, str] = {
    "fit": "learner.fit",
    "tune": "learner.tune",
    "info": "learner.info",
    "plot": "learner.plots",
    "track": "learner.track",
    "policy": "learner.planning",
    "evaluate": "learner.evaluate",
    "closed-loop": "learner.closed_loop_cli",
    "experiment": "learner.experiment",
    "study": "learner.study",
    "competence": "learner.competence",
    "report": "learner.report",
    "memory": "learner.memory",
    "view-study": "learner.view_study",
    "view-figure": "learner.view_figure",
    "demo": "learner.demo",
}
"""Every subcommand and the module that adds it, in the order of ``learner --help``."""


def _mount_main(subparsers: Any, name: str, module: Any) -> None:
    doc = (module.__doc__ or "").strip().split("\n")[0]
    parser = subparsers.add_parser(name, help=doc, description=doc, add_help=False)
    parser.add_argument("argv", nargs=argparse.REMAINDER)
    parser.set_defaults(run=lambda args: module.main(args.argv))


def _pass_through(argv: list[str]) -> Any:
    """Return the ``main`` of the pass-through subcommand named by ``argv[0]``, or None."""
    if not argv or argv[0] not in SUBCOMMANDS:
        return None
    module = importlib.import_module(SUBCOMMANDS[argv[0]])
    if not hasattr(module, "register") and hasattr(module, "main"):
        return module.main
    return None


def build_parser(command: str | None = None) -> ArgumentParser:
    """Build the ``learner`` parser with every subcommand of :data:`SUBCOMMANDS`, or
    with ``command`` alone when it names one: only its module is imported, so a command
    starts without loading what the others need (the report's page, the studies' SciPy)."""
    chosen = {command: SUBCOMMANDS[command]} if command in SUBCOMMANDS else SUBCOMMANDS
    parser = ArgumentParser(
        prog=PROG,
        description="Offline TPSR learning: bags -> model -> states, plots and policies.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in chosen.items():
        module = importlib.import_module(module_name)
        if hasattr(module, "register"):
            module.register(subparsers)
        elif hasattr(module, "main"):
            _mount_main(subparsers, name, module)
        else:
            raise RuntimeError(f"{module_name} has neither register(subparsers) nor main(argv)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` and run the chosen subcommand; ``TpsrError`` propagates."""
    argv = sys.argv[1:] if argv is None else argv
    if (pass_through := _pass_through(argv)) is not None:
        return int(pass_through(argv[1:]) or 0)  # its own parser sees every option
    args = build_parser(argv[0] if argv else None).parse_args(argv)
    return int(args.run(args) or 0)


def entry(argv: list[str] | None = None) -> None:
    """Console entry: :func:`main` with one-line errors and exit codes."""
    run_cli(PROG, lambda: main(argv))
