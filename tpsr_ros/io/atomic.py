"""Files written whole or not at all: a temporary file beside the target, then a rename.

Why: a model, a config or a bag's ``metadata.yaml`` that a crash (or a full disk) leaves
half written would be read later as damaged input, and an existing good file would be
lost. Writing to a new temporary file in the same directory (``mkstemp``: exclusive, never
through a link), flushing it to disk and renaming it over the target (``os.replace``,
atomic on POSIX) means a reader sees the old file or the new one, never a part. The new
file gets the permissions a plain ``open`` would give it: the replaced file's, or for a new
name ``0o666`` less the process umask (``mkstemp`` alone would make it ``0o600``, so a
model or a bag's ``metadata.yaml`` would be unreadable to other users).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_file"]


@contextmanager
def atomic_file(
    path: Path | str, mode: str = "wb", *, sync: bool = True, permissions: int | None = None
) -> Iterator[IO[Any]]:
    """A file opened with ``mode`` that replaces ``path`` when the block ends without error.

    On an error in the block (the caller may raise one to give up) the temporary file is
    removed and ``path`` is left as it was. ``sync`` flushes the data to disk before the
    rename (off for files that are cheap to rewrite). ``permissions`` sets the new file's
    mode where the replaced file's must not carry over (a file others could write).
    """
    target = Path(path)
    if permissions is None:
        permissions = _permissions_for(target)
    # in the directory that holds the name (not where a link at it points): same file system
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    temporary = Path(name)
    try:
        os.fchmod(fd, permissions)
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as handle:
            yield handle
            handle.flush()
            if sync:
                os.fsync(handle.fileno())
        os.replace(temporary, target)
    finally:
        temporary.unlink(missing_ok=True)


def _permissions_for(target: Path) -> int:
    """The mode ``open(target, "w")`` would leave: the existing file's, else 0o666 & ~umask."""
    if target.is_symlink():  # the link is replaced, not followed: a new file
        return _default_mode()
    try:
        return target.stat().st_mode & 0o777
    except FileNotFoundError:
        return _default_mode()


def _default_mode() -> int:
    """``0o666`` less the umask, read from /proc where it is shown (no process-wide change)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # elsewhere: read it by setting it, and put it back at once
    os.umask(mask)
    return 0o666 & ~mask
