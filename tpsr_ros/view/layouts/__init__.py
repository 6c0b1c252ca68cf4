"""The layouts that ship with tpsr-ros: Foxglove, RViz2 and PlotJuggler views of the state.

    python -m tpsr_ros.view.layouts --check        # the files here equal what the code builds
    python -m tpsr_ros.view.layouts --write DIR    # write them to DIR (default: here)

Each layout is built in code from :data:`~tpsr_ros.view.topics.VIEW_TOPICS` (a topic
missing from that table fails the build) and checked in next to this file as package
data; colcon installs them into ``share/tpsr_ros/layouts/``. ``tests/test_layouts.py``
checks every topic and field path they read against the ROS 2 Jazzy message definitions.

- :data:`FOXGLOVE_FILE` (:mod:`.foxglove_json`, needs foxglove-sdk): camera and predicted
  image side by side, the state markers in 3D, the state's time series, the phase plot
  b1 against b2, decoded against true pose, diagnostics and parameters;
- :data:`RVIZ_FILE` (:mod:`.rviz`): fixed frame ``tpsr``, the state markers and both
  images;
- :data:`PLOTJUGGLER_FILE` (:mod:`.plotjuggler`): the state's time series, the phase
  plot and decoded against true position, streamed from ROS 2.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

from tpsr_ros.cli import ArgumentParser
from tpsr_ros.core.errors import TpsrError
from tpsr_ros.view.server import require_sdk
from tpsr_ros.view.topics import VIEW_TOPICS, default_topic

__all__ = [
    "FOXGLOVE_FILE",
    "LAYOUT_FILES",
    "PLOTJUGGLER_FILE",
    "PROG",
    "RVIZ_FILE",
    "SHIPPED",
    "build_layouts",
    "main",
    "topic",
    "write_layouts",
]

FOXGLOVE_FILE = "tpsr_view.foxglove.json"
RVIZ_FILE = "tpsr_view.rviz"
PLOTJUGGLER_FILE = "tpsr_view.plotjuggler.xml"
LAYOUT_FILES = (FOXGLOVE_FILE, RVIZ_FILE, PLOTJUGGLER_FILE)
SHIPPED = Path(__file__).resolve().parent
"""Where the checked-in layouts are (package data)."""

PROG = "python -m tpsr_ros.view.layouts"


def topic(name: str) -> str:
    """Name view topic ``name`` as the layouts do (the default namespace); KeyError if unknown."""
    VIEW_TOPICS[name]
    return default_topic(name)


def _builders() -> dict[str, Callable[[], str]]:
    require_sdk()  # foxglove.layouts builds the Foxglove layout
    from tpsr_ros.view.layouts.foxglove_json import foxglove_layout
    from tpsr_ros.view.layouts.plotjuggler import plotjuggler_layout
    from tpsr_ros.view.layouts.rviz import rviz_config

    return {
        FOXGLOVE_FILE: foxglove_layout,
        RVIZ_FILE: rviz_config,
        PLOTJUGGLER_FILE: plotjuggler_layout,
    }


def build_layouts() -> dict[str, str]:
    """File name -> text of every shipped layout."""
    return {name: build() for name, build in _builders().items()}


def write_layouts(directory: Path) -> list[Path]:
    """Write every layout into ``directory`` (created if missing); the paths written."""
    layouts = build_layouts()
    written = []
    try:
        directory.mkdir(parents=True, exist_ok=True)
        for name, text in layouts.items():
            path = directory / name
            path.write_text(text, encoding="utf-8")
            written.append(path)
    except OSError as exc:
        raise TpsrError(f"cannot write the layouts to {str(directory)!r}: {exc.strerror}") from None
    return written


def _stale(directory: Path) -> list[str]:
    """Layouts in ``directory`` that differ from what the code builds (or are missing)."""
    stale = []
    for name, text in build_layouts().items():
        path = directory / name
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            stale.append(name)
    return stale


def main(argv: list[str] | None = None) -> int:
    """Write or check the layouts; 1 when ``--check`` finds a difference."""
    parser = ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--write", type=Path, nargs="?", const=SHIPPED, metavar="DIR",
                       help=f"write the layouts to DIR (default: {SHIPPED})")
    group.add_argument("--check", action="store_true",
                       help="exit 1 when a checked-in layout differs from what the code builds")
    args = parser.parse_args(argv)
    if args.check:
        stale = _stale(SHIPPED)
        if stale:
            print(f"{PROG}: stale: {', '.join(stale)} (run {PROG} --write)", file=sys.stderr)
            return 1
        print(f"{len(LAYOUT_FILES)} layouts up to date in {SHIPPED}")
        return 0
    for path in write_layouts(args.write):
        print(path)
    return 0
