"""Errors of tpsr-ros, catchable by name.

Every error a user can cause (bad file, bad parameter, bad message) is a ``TpsrError``
subclass whose message is one sentence naming the problem; command-line entry points
print it on one line and exit non-zero.
"""

from __future__ import annotations

__all__ = [
    "BagError",
    "ConfigError",
    "DataError",
    "DivergenceError",
    "EncodingError",
    "MessageError",
    "ModelFormatError",
    "NotFittedError",
    "TpsrError",
    "one_line",
]


def one_line(exc: BaseException, limit: int = 200) -> str:
    """A foreign exception's text on one line (whitespace collapsed), cut to ``limit`` chars.

    For wrapping library errors (zip, zstd, mcap...) into our one-line messages.
    """
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."


class TpsrError(Exception):
    """Base class of every error tpsr-ros raises on purpose."""


class ConfigError(TpsrError, ValueError):
    """A configuration value or parameter is invalid."""


class BagError(TpsrError):
    """A bag cannot be read or written (missing, foreign format, existing path...)."""


class MessageError(TpsrError, ValueError):
    """A message has the wrong type, size, encoding or frame."""


class EncodingError(MessageError):
    """A message's data is in an encoding or format that cannot be read (not damaged data)."""


class DataError(TpsrError, ValueError):
    """Training or evaluation data are unusable (too few episodes, non-finite values...)."""


class DivergenceError(DataError):
    """Fitted Q-iteration diverged or did not converge (a larger ridge may settle it)."""


class ModelFormatError(TpsrError):
    """A model or policy file is truncated, foreign, or of another format version."""


class NotFittedError(TpsrError, RuntimeError):
    """A learner was used before ``fit``."""
