"""Progress for long commands: a bar on a terminal, plain periodic lines in a log.

A progress bar redraws itself with carriage returns, which a terminal shows as one moving
line and a log file keeps as noise. :func:`progress_bar` draws a ``tqdm`` bar only when
its stream is a terminal; otherwise it writes a line ``desc: n/total unit (p %)`` at most
every :data:`LINE_PERIOD_S` seconds, and one at the end.
"""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

__all__ = ["LINE_PERIOD_S", "LineProgress", "progress_bar"]

LINE_PERIOD_S = 10.0
"""Seconds between progress lines when the output is not a terminal."""


class LineProgress:
    """The part of ``tqdm``'s interface the commands use, as plain lines."""

    def __init__(
        self, total: int | None, desc: str, unit: str, file: TextIO, period_s: float
    ) -> None:
        self.total, self.desc, self.unit, self.file = total, desc, unit, file
        self.period_s = period_s
        self.n = 0
        self.postfix = ""
        self._started = self._said = time.monotonic()
        self._closed = False

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        """``n`` more done; a line if the last one is :attr:`period_s` old."""
        self.n += n
        now = time.monotonic()
        if now - self._said >= self.period_s:
            self._said = now
            self._line()

    def set_postfix(self, **values: Any) -> None:
        """Values shown after the count (``tqdm.set_postfix``)."""
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def write(self, text: str, file: TextIO | None = None) -> None:
        """A message of its own (``tqdm.write``)."""
        print(text, file=file or self.file, flush=True)

    def close(self) -> None:
        """The last line (once)."""
        if not self._closed:
            self._closed = True
            self._line()

    def _line(self) -> None:
        of = f"/{self.total}" if self.total else ""
        share = f" ({100 * self.n / self.total:.0f} %)" if self.total else ""
        seconds = time.monotonic() - self._started
        extra = f", {self.postfix}" if self.postfix else ""
        print(
            f"{self.desc}: {self.n}{of} {self.unit}{share}, {seconds:.0f} s{extra}",
            file=self.file,
            flush=True,
        )


class _Silent(LineProgress):
    def _line(self) -> None:
        return None


def progress_bar(
    *,
    total: int | None,
    desc: str,
    unit: str,
    disable: bool = False,
    file: TextIO | None = None,
    period_s: float = LINE_PERIOD_S,
) -> Any:
    """A ``tqdm`` bar on a terminal (``file``, default stderr), else a :class:`LineProgress`;
    ``disable``: nothing shown (messages given to ``write`` still are)."""
    stream = file if file is not None else sys.stderr
    if disable:
        return _Silent(total, desc, unit, stream, period_s)
    isatty = getattr(stream, "isatty", None)
    if callable(isatty) and isatty():
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit=unit, file=stream)
    return LineProgress(total, desc, unit, stream, period_s)
