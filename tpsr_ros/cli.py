"""Command-line plumbing shared by every tpsr-ros command: one-line errors, exit codes."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from typing import NoReturn

from tpsr_ros.core.errors import TpsrError

__all__ = [
    "ROS_ARGUMENT_FLAGS",
    "ArgumentParser",
    "non_negative_int",
    "positive_float",
    "positive_int",
    "ros_args_hint",
    "run_cli",
]


class ArgumentParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose errors are a single line ``prog: error: ...``."""

    def error(self, message: str) -> NoReturn:
        """Print one line naming the problem and exit with status 2 (with a hint where ROS
        arguments were given without ``--ros-args`` before them)."""
        self.exit(2, f"{self.prog}: error: {message}{ros_args_hint(message, self.prog)}\n")


ROS_ARGUMENT_FLAGS = frozenset(
    {"-p", "--param", "-r", "--remap", "--params-file", "--log-level", "-e", "--enclave"}
)
"""Arguments of ROS 2's command line, which only count after ``--ros-args``."""


def ros_args_hint(message: str, prog: str) -> str:
    """A hint for an ``unrecognized arguments`` error that names ROS arguments: they go
    after ``--ros-args``, as for any ROS 2 node; "" otherwise."""
    prefix = "unrecognized arguments: "
    if not message.startswith(prefix):
        return ""
    tokens = message[len(prefix):].split()
    if not any(t in ROS_ARGUMENT_FLAGS or t.split("=")[0] in ROS_ARGUMENT_FLAGS for t in tokens):
        return ""
    given = " ".join(tokens)
    return f" (ROS arguments go after --ros-args, as for any ROS 2 node: {prog} --ros-args {given})"


def _number(text: str, kind: type[int] | type[float], noun: str) -> int | float:
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not {noun}") from None


def positive_int(text: str) -> int:
    """argparse type: an integer > 0."""
    value = int(_number(text, int, "an integer"))
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{value} is not positive")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    value = int(_number(text, int, "an integer"))
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is negative")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = float(_number(text, float, "a number"))
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{value} is not positive")
    if value == float("inf"):
        raise argparse.ArgumentTypeError(f"{value} is not finite")
    return value


def run_cli(prog: str, main: Callable[[], int | None]) -> NoReturn:
    """Run ``main``; a ``TpsrError`` or Ctrl-C is one line on stderr and a non-zero exit."""
    try:
        code = main()
    except TpsrError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        sys.exit(130)
    except BrokenPipeError:  # `... | head` closed our stdout: stop quietly, as cat does
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(141)
    sys.exit(code or 0)
