"""Command-line plumbing shared by every tpsr-ros command: one-line errors, exit codes."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import NoReturn

from tpsr_ros.errors import TpsrError

__all__ = ["ArgumentParser", "positive_int", "run_cli"]


class ArgumentParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose errors are a single line ``prog: error: ...``."""

    def error(self, message: str) -> NoReturn:
        """Print one line naming the problem and exit with status 2."""
        self.exit(2, f"{self.prog}: error: {message}\n")


def positive_int(text: str) -> int:
    """argparse type: an integer > 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{value} is not positive")
    return value


def run_cli(prog: str, main: Callable[[], int | None]) -> NoReturn:
    """Run ``main``; a ``TpsrError`` or Ctrl-C becomes one line on stderr and a non-zero exit."""
    try:
        code = main()
    except TpsrError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        sys.exit(130)
    sys.exit(code or 0)
