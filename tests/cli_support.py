"""Running ``python -m learner`` in-process, as a user would, for the learner's tests.

Imported by the test modules (``from cli_support import run_entry``; pytest puts
``tests/`` on ``sys.path``).
"""

from __future__ import annotations

import pytest

from learner.cli import entry


def run_entry(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``(exit status, stdout, stderr)`` of ``python -m learner ARGV``."""
    with pytest.raises(SystemExit) as exc:
        entry(argv)
    out, err = capsys.readouterr()
    return exc.value.code, out, err
