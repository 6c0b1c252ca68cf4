"""Node processes started together: start, wait for the graph, stop, collect exit status.

One launcher for everything that spawns nodes (``learner closed-loop``, the multi-process
tests, the benchmarks), like a small ``ros2 launch``:

- :class:`NodeProcess` runs ``python -m MODULE ARGS...`` with its own environment; stdout
  and stderr go to one log file, and/or line by line to an ``on_output`` callback (how
  ``python -m tpsr_ros.launch`` prefixes each node's output, like ``ros2 launch``).
  On Linux the child gets SIGTERM if this process dies
  (``prctl(PR_SET_PDEATHSIG)``), so a crashed or killed parent leaves no orphan, and
  SIGINT's default back where this process ignores it (a script's background job).
  :meth:`NodeProcess.stop` sends SIGINT (a node's graceful shutdown), waits, and kills it
  if it does not exit.
- :class:`Launch` holds the processes of one run. :meth:`Launch.wait` spins the caller's
  own node (or sleeps) until a condition on the graph holds: a subscription count, a
  message received on a topic. It fails with a one-line :class:`LaunchError` as soon as a
  process exits or the timeout passes. Leaving the ``with`` block stops every process, the
  last started first.

Handshakes go through the graph, never through log text: the logs are for people.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO

from tpsr_ros.core.errors import TpsrError

__all__ = ["Launch", "LaunchError", "NodeProcess", "environ_overrides"]

# Run a module so that it gets SIGTERM when its parent dies (Linux prctl PR_SET_PDEATHSIG)
# and stops on SIGINT even where the parent ignores SIGINT (a script's background job, a
# process that ran a node in it: Python leaves an inherited ignored SIGINT ignored, and a
# node that has not yet installed its handlers would lose the launcher's SIGINT and be
# killed after the stop timeout), then exactly as `python -m MODULE ARGS...`.
_LAUNCH = """\
import ctypes, os, runpy, signal, sys
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
except Exception:
    pass
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
if os.getppid() != int(sys.argv[1]):
    sys.exit(1)
module = sys.argv[2]
sys.argv = [module] + sys.argv[3:]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""


class LaunchError(TpsrError):
    """A launched node exited while it was needed, or a wait on the graph timed out."""


class NodeProcess:
    """``python -m module args...`` as a child process.

    Its stdout and stderr (merged) go to ``log_path`` if given; with ``on_output`` they
    are read through a pipe by a thread that also calls ``on_output(line)`` for each line
    (without its newline). With neither, the child inherits this process's output.
    """

    def __init__(
        self,
        name: str,
        module: str,
        args: Sequence[str] = (),
        *,
        log_path: Path | str | None = None,
        env: Mapping[str, str] | None = None,
        die_with_parent: bool = True,
        on_output: Callable[[str], None] | None = None,
    ) -> None:
        self.name = name
        self.module = module
        self.command = ["python", "-m", module, *args]
        self.log_path = None if log_path is None else Path(log_path)
        self.on_output = on_output
        self._recent: deque[str] = deque(maxlen=200)
        self._pump: threading.Thread | None = None
        environment = {**(os.environ if env is None else env), "PYTHONUNBUFFERED": "1"}
        if die_with_parent:
            argv = [sys.executable, "-c", _LAUNCH, str(os.getpid()), module, *args]
        else:
            argv = [sys.executable, "-m", module, *args]
        if on_output is None and self.log_path is not None:
            with self.log_path.open("wb") as sink:
                self.popen = self._spawn(argv, environment, sink)
        elif on_output is None:
            self.popen = self._spawn(argv, environment, None)
        else:
            sink = None if self.log_path is None else self.log_path.open("wb")
            try:
                self.popen = self._spawn(argv, environment, subprocess.PIPE)
            except BaseException:
                if sink is not None:
                    sink.close()
                raise
            assert self.popen.stdout is not None
            self._pump = threading.Thread(
                target=self._copy_output, args=(self.popen.stdout, sink),
                name=f"{name} output", daemon=True,
            )  # fmt: skip
            self._pump.start()

    @staticmethod
    def _spawn(
        argv: list[str], env: dict[str, str], stdout: IO[bytes] | int | None
    ) -> subprocess.Popen[bytes]:
        """Start the child, stderr merged into stdout (unless inherited)."""
        return subprocess.Popen(
            argv, stdin=subprocess.DEVNULL, stdout=stdout,
            stderr=None if stdout is None else subprocess.STDOUT, env=env,
        )  # fmt: skip

    def _copy_output(self, stream: IO[bytes], sink: IO[bytes] | None) -> None:
        """Reader thread: each line to the log file, the recent lines and ``on_output``."""
        assert self.on_output is not None
        try:
            for raw in stream:
                if sink is not None:
                    sink.write(raw)
                    sink.flush()
                line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
                self._recent.append(line)
                self.on_output(line)
        finally:
            stream.close()
            if sink is not None:
                sink.close()

    def _drain(self, timeout_s: float = 5.0) -> None:
        """After the exit: let the reader thread pass on the last lines."""
        if self._pump is not None:
            self._pump.join(timeout_s)

    @property
    def pid(self) -> int:
        """Process id of the child."""
        return int(self.popen.pid)

    @property
    def returncode(self) -> int | None:
        """Exit status once the process has exited (negative: killed by that signal)."""
        return self.popen.poll()

    def alive(self) -> bool:
        """Return whether the process is still running."""
        return self.popen.poll() is None

    def text(self) -> str:
        """Everything the process has written so far (without a log file: its last lines)."""
        if self.log_path is None:
            return "\n".join(self._recent)
        try:
            return self.log_path.read_text(encoding="utf-8", errors="replace")
        except FileNotFoundError:
            return ""

    def tail(self, n: int = 8) -> str:
        """Return the last ``n`` lines of output."""
        return "\n".join(self.text().splitlines()[-n:])

    def wait(self, timeout_s: float) -> int:
        """Wait for the process to exit by itself; its exit status."""
        try:
            code = self.popen.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise LaunchError(f"{self.name} did not exit within {timeout_s:g} s") from None
        self._drain()
        return code

    def stop(self, timeout_s: float = 20.0, sig: int = signal.SIGINT) -> int:
        """Send ``sig`` (SIGINT: a node's graceful shutdown), wait; SIGKILL if it hangs."""
        if self.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
        code = int(self.popen.wait())
        self._drain()
        return code

    def kill(self) -> None:
        """SIGKILL, and reap the process."""
        if self.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.popen.kill()
        self.popen.wait(10)
        self._drain()


class Launch:
    """The node processes of one run, their logs in ``log_dir`` (None: no log files).

    ``spin(timeout_s)`` is what :meth:`wait` does between checks, typically the
    ``spin_once`` of the caller's own node so that its subscriptions receive messages;
    default: sleep. ``on_output(name, line)``, if given, receives every line each process
    writes (from one reader thread per process).
    """

    def __init__(
        self,
        log_dir: Path | str | None,
        *,
        env: Mapping[str, str] | None = None,
        spin: Callable[[float], object] | None = None,
        timeout_s: float = 60.0,
        on_output: Callable[[str, str], None] | None = None,
    ) -> None:
        self.log_dir = None if log_dir is None else Path(log_dir)
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = dict(os.environ if env is None else env)
        self.spin = spin or time.sleep
        self.timeout_s = timeout_s
        self.on_output = on_output
        self.processes: dict[str, NodeProcess] = {}

    def start(
        self,
        name: str,
        module: str,
        args: Sequence[str] = (),
        *,
        env: Mapping[str, str] | None = None,
    ) -> NodeProcess:
        """Start ``python -m module args...`` as ``name`` (log ``log_dir/name.log``)."""
        if name in self.processes:
            raise LaunchError(f"a process named {name!r} was already started")
        on_output = self.on_output
        process = NodeProcess(
            name, module, args,
            log_path=None if self.log_dir is None else self.log_dir / f"{name}.log",
            env=self.env if env is None else env,
            on_output=None if on_output is None else (lambda line: on_output(name, line)),
        )  # fmt: skip
        self.processes[name] = process
        return process

    def exited(self) -> dict[str, int]:
        """Exit statuses of the processes that have exited, in order of start."""
        return {
            name: code
            for name, process in self.processes.items()
            if (code := process.returncode) is not None
        }

    def wait(
        self, what: str, condition: Callable[[], bool], timeout_s: float | None = None
    ) -> None:
        """Spin until ``condition()``; fail if a process exits or after the timeout."""
        limit = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + limit
        while not condition():
            for process in self.processes.values():
                if not process.alive():
                    raise LaunchError(
                        f"{process.name} exited with status {process.returncode} while "
                        f"waiting for {what}: {process.tail(3)!r}"
                    )
            if time.monotonic() > deadline:
                raise LaunchError(f"timed out after {limit:g} s waiting for {what}")
            self.spin(0.02)

    def stop(self, timeout_s: float = 20.0) -> dict[str, int]:
        """SIGINT each process, the last started first; their exit statuses."""
        return {
            name: self.processes[name].stop(timeout_s) for name in reversed(list(self.processes))
        }

    def __enter__(self) -> Launch:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()


@contextlib.contextmanager
def environ_overrides(overrides: Mapping[str, str]) -> Iterator[None]:
    """``os.environ`` with ``overrides`` set inside the block, as it was after it: what the
    processes started inside inherit."""
    saved = {key: os.environ.get(key) for key in overrides}
    os.environ.update(overrides)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
