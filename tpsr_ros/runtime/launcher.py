"""Node processes started together: start, wait for the graph, stop, collect exit status.

One launcher for everything that spawns nodes (``learner closed-loop``, the multi-process
tests, the benchmarks), like a small ``ros2 launch``:

- :class:`NodeProcess` runs ``python -m MODULE ARGS...`` with its own environment; stdout
  and stderr go to one log file. On Linux the child gets SIGTERM if this process dies
  (``prctl(PR_SET_PDEATHSIG)``), so a crashed or killed parent leaves no orphan.
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
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import TracebackType

from tpsr_ros.core.errors import TpsrError

__all__ = ["Launch", "LaunchError", "NodeProcess"]

# Run a module so that it gets SIGTERM when its parent dies (Linux prctl PR_SET_PDEATHSIG),
# then exactly as `python -m MODULE ARGS...`.
_LAUNCH = """\
import ctypes, os, runpy, signal, sys
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
except Exception:
    pass
if os.getppid() != int(sys.argv[1]):
    sys.exit(1)
module = sys.argv[2]
sys.argv = [module] + sys.argv[3:]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""


class LaunchError(TpsrError):
    """A launched node exited while it was needed, or a wait on the graph timed out."""


class NodeProcess:
    """``python -m module args...`` as a child process logging to ``log_path``."""

    def __init__(
        self,
        name: str,
        module: str,
        args: Sequence[str] = (),
        *,
        log_path: Path | str,
        env: Mapping[str, str] | None = None,
        die_with_parent: bool = True,
    ) -> None:
        self.name = name
        self.module = module
        self.command = ["python", "-m", module, *args]
        self.log_path = Path(log_path)
        environment = {**(os.environ if env is None else env), "PYTHONUNBUFFERED": "1"}
        if die_with_parent:
            argv = [sys.executable, "-c", _LAUNCH, str(os.getpid()), module, *args]
        else:
            argv = [sys.executable, "-m", module, *args]
        with self.log_path.open("wb") as sink:
            self.popen = subprocess.Popen(
                argv, stdin=subprocess.DEVNULL, stdout=sink, stderr=subprocess.STDOUT,
                env=environment,
            )  # fmt: skip

    @property
    def returncode(self) -> int | None:
        """Exit status once the process has exited (negative: killed by that signal)."""
        return self.popen.poll()

    def alive(self) -> bool:
        """Return whether the process is still running."""
        return self.popen.poll() is None

    def text(self) -> str:
        """Everything the process has written so far."""
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
            return self.popen.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise LaunchError(f"{self.name} did not exit within {timeout_s:g} s") from None

    def stop(self, timeout_s: float = 20.0, sig: int = signal.SIGINT) -> int:
        """Send ``sig`` (SIGINT: a node's graceful shutdown), wait; SIGKILL if it hangs."""
        if self.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
        return int(self.popen.wait())

    def kill(self) -> None:
        """SIGKILL, and reap the process."""
        if self.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.popen.kill()
        self.popen.wait(10)


class Launch:
    """The node processes of one run, their logs in ``log_dir``.

    ``spin(timeout_s)`` is what :meth:`wait` does between checks, typically the
    ``spin_once`` of the caller's own node so that its subscriptions receive messages;
    default: sleep.
    """

    def __init__(
        self,
        log_dir: Path | str,
        *,
        env: Mapping[str, str] | None = None,
        spin: Callable[[float], object] | None = None,
        timeout_s: float = 60.0,
    ) -> None:
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = dict(os.environ if env is None else env)
        self.spin = spin or time.sleep
        self.timeout_s = timeout_s
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
        process = NodeProcess(
            name, module, args, log_path=self.log_dir / f"{name}.log",
            env=self.env if env is None else env,
        )  # fmt: skip
        self.processes[name] = process
        return process

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
