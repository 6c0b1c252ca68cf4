"""The filter node's steps without ROS: two step sources behind one interface.

A step source turns the node's input messages, one at a time in arrival order, into the
steps offline tracking makes of the same messages: ``(t_k, a_k, o_k)``.

- :class:`ExactPairing` (simulator streams, DESIGN.md): the image and the executed action of
  step k carry the identical stamp t_k and are paired by it
  (:class:`~tpsr_ros.core.pairing.ExactTimeSynchronizer`). Stamps one step period apart make
  a steady cadence, so a gap of n periods on an input means n - 1 lost messages.
- :class:`GridStepping` (models learned with ``--step-period``): camera and commands are
  resampled on the model's step grid (:class:`~tpsr_ros.core.resample.GridStepper`), the
  latest image and the command in force at each grid time.
- :class:`LockstepStepping` (the same models driving a robot that takes one step per
  command and answers it with one image, as ``sim_node`` in command mode does): each image
  is one step on the model's grid, with the node's own last command as its action. The
  grid rules cannot close a step there: they wait for an image after the step, which the
  robot sends only once the node has answered that step.

Both answer ``add_image`` and ``add_action`` with :class:`Added` (the completed steps and
whether time jumped back, which restarts the state) and report their counters with
:meth:`counts`.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import Any, Protocol

from tpsr_ros.core.cadence import CadenceGaps
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.pairing import ExactTimeSynchronizer, Outcome
from tpsr_ros.core.resample import GridConfig, GridStep, GridStepper

__all__ = [
    "Added",
    "CommandDating",
    "ExactPairing",
    "GridStepping",
    "LockstepStepping",
    "Step",
    "StepSource",
]


@dataclass(frozen=True)
class Step:
    """One step to track: its stamp, action index and image content.

    ``image`` is what was given to ``add_image``: the observation (:class:`ExactPairing`),
    or whatever holds it (:class:`GridStepping`: the node's frame, decoded later).
    """

    stamp: int
    action: int
    image: Any


@dataclass(frozen=True)
class Added:
    """What one input message did.

    Attributes:
        steps: the steps it completed, in stamp order.
        jumped: time jumped back before it: the state restarts, the steps follow.
        problem: ``"duplicate"``, ``"late"`` or ``"dropped"`` when the message or older
            incomplete steps were discarded (worth a throttled warning), else None.

    """

    steps: list[Step] = field(default_factory=list)
    jumped: bool = False
    problem: str | None = None


class StepSource(Protocol):
    """Input messages to steps; see the module docstring."""

    def add_image(self, stamp: int, image: Any) -> Added:
        """An image message's content at ``stamp``."""

    def add_action(self, stamp: int, action: int) -> Added:
        """An action index at ``stamp``."""

    def episode_start(self, stamp: int) -> bool:
        """An episode starts after ``stamp``: True if the state restarts, False if stale."""

    def clock(self, stamp: int) -> bool:
        """The clock's time; True if it jumped back (the state restarts)."""

    def counts(self) -> dict[str, int]:
        """Counters for ``/diagnostics``, in report order."""


class ExactPairing:
    """Simulator streams paired by identical stamp, with loss counted from stamp gaps."""

    def __init__(self, step_ns: int, *, queue_size: int, jump_threshold_ns: int) -> None:
        self.step_ns = int(step_ns)
        self.sync = ExactTimeSynchronizer(
            2, queue_size=queue_size, jump_threshold_ns=jump_threshold_ns
        )
        self.lost = {"image": 0, "action": 0}
        self._last_stamp: dict[str, int | None] = {"image": None, "action": None}

    def _count_lost(self, which: str, stamp: int) -> None:
        """Steps lost on one input, from the gaps in its stamps.

        Simulator step k is stamped k periods after time 0 or after its episode start
        (DESIGN.md), so a stamp n periods after the previous one on the input (or after
        time 0, or the last episode start) means n - 1 lost steps. A backwards jump of
        time starts the count afresh from time 0.
        """
        last = self._last_stamp[which]
        if last is None or stamp < last - self.sync.jump_threshold_ns:
            last = 0
        if stamp > last and (stamp - last) % self.step_ns == 0:
            self.lost[which] += (stamp - last) // self.step_ns - 1
        if stamp > last:
            self._last_stamp[which] = stamp

    def _add(self, index: int, stamp: int, item: Any) -> Added:
        self._count_lost(("image", "action")[index], stamp)
        dropped_before = self.sync.stats.dropped
        result = self.sync.add(index, stamp, item)
        problem = None
        if self.sync.stats.dropped > dropped_before:
            problem = "dropped"
        if result.outcome is Outcome.DUPLICATE:
            problem = "duplicate"
        elif result.outcome is Outcome.LATE:
            problem = "late"
        steps = []
        if result.outcome is Outcome.PAIRED:
            assert result.items is not None
            image, action = result.items
            steps.append(Step(stamp, int(action), image))
        return Added(steps, result.jumped, problem)

    def add_image(self, stamp: int, image: Any) -> Added:
        """An image's observation (see :class:`StepSource`)."""
        return self._add(0, stamp, image)

    def add_action(self, stamp: int, action: int) -> Added:
        """An executed action's index (see :class:`StepSource`)."""
        return self._add(1, stamp, action)

    def episode_start(self, stamp: int) -> bool:
        """A start newer than the last step (or a jump back) restarts; older ones are stale."""
        last = self.sync.last_stamp
        if last is not None and stamp <= last and not self.sync.check_time(stamp):
            return False
        self.sync.start_after(stamp)
        for which in self._last_stamp:  # step 1 of the episode comes one period later
            self._last_stamp[which] = stamp
        return True

    def clock(self, stamp: int) -> bool:
        """``/clock``: a jump back clears the pairing buffer."""
        return self.sync.check_time(stamp)

    @property
    def last_stamp(self) -> int | None:
        """Stamp of the last paired step (or the last episode start)."""
        return self.sync.last_stamp

    def counts(self) -> dict[str, int]:
        """Pairing counters and the steps lost by stamps."""
        stats = self.sync.stats
        return {
            "dropped": stats.dropped,
            "duplicates": stats.duplicates,
            "late": stats.late,
            "out_of_order": stats.out_of_order,
            "time_jumps": stats.time_jumps,
            "lost_images": self.lost["image"],
            "lost_actions": self.lost["action"],
        }


class CommandDating:
    """Unstamped commands dated by the first image sent after them, as a bag's order dates
    them offline (:mod:`tpsr_ros.core.resample`).

    ``sent`` is when a message was published (the middleware's source timestamp, or its
    arrival where there is none): the order of sending, not of the callbacks, decides, so
    a replay gives every command the date it has offline. A command sent after the newest
    image waits for the next one; a command handled after images sent later than it takes
    the first of those (the last :data:`HISTORY` images are kept for that).
    """

    HISTORY = 256

    def __init__(self) -> None:
        self._images: list[tuple[int, int]] = []  # (sent, stamp), in sending order
        self._waiting: list[tuple[int, Any]] = []  # (sent, command) sent after the newest

    def reset(self) -> None:
        """Forget images and waiting commands (time jumped back)."""
        self._images.clear()
        self._waiting.clear()

    def image(self, sent: int, stamp: int) -> list[tuple[int, Any]]:
        """An image; returns the waiting commands it dates, as ``(date, command)``."""
        if self._images and sent <= self._images[-1][0]:
            self._images.clear()  # the sender's clock went back: a new stream
        self._images.append((int(sent), int(stamp)))
        del self._images[: -self.HISTORY]
        dated = [(int(stamp), c) for t, c in self._waiting if t < sent]
        self._waiting = [(t, c) for t, c in self._waiting if t >= sent]
        return dated

    def command(self, sent: int, command: Any) -> tuple[int, Any] | None:
        """A command: ``(date, command)`` if an image was sent after it, else None (waits)."""
        index = bisect.bisect_right(self._images, sent, key=lambda pair: pair[0])
        if index < len(self._images):
            return self._images[index][1], command
        self._waiting.append((int(sent), command))
        return None


class GridStepping:
    """Robot streams resampled on the model's step grid; lost images from the camera's cadence.

    Images are given as they arrive (any object; a step holds the image in force at its
    time) and commands as action indices; ``far_commands`` counts the command messages
    farther from every code than the codebook's ``far_distance``, among the
    ``command_messages`` put in force (dated), as ``learner fit`` counts a bag's.
    ``max_latency_ns``: how far one stream may run
    ahead of a step before the step closes without the other (:class:`GridStepper`).
    """

    def __init__(
        self, grid: GridConfig, *, jump_threshold_ns: int, max_latency_ns: int = 10**9
    ) -> None:
        self.stepper = GridStepper(grid, max_latency_ns)
        self.jump_threshold_ns = int(jump_threshold_ns)
        self.cadence = CadenceGaps()
        self.dating = CommandDating()
        self.time_jumps = 0
        self.far_commands = 0

    @property
    def last_image_time(self) -> int | None:
        """Stamp of the newest image (ns), or None."""
        return self.stepper.last_image_time

    @property
    def lost_images(self) -> int:
        """Images missing from the camera's cadence (lower when it proves to stretch frames)."""
        return self.cadence.missing

    def _jumped(self, stamp: int) -> bool:
        """Whether ``stamp`` is a backward jump of the stream's time; if so, restart the grid."""
        last = self.stepper.last_image_time
        if last is None or stamp >= last - self.jump_threshold_ns:
            return False
        self.stepper.reset()
        self.dating.reset()
        self.time_jumps += 1
        return True

    def add_image(self, stamp: int, image: Any, sent_ns: int = 0) -> Added:
        """An image (``sent_ns``: when it was published, to date unstamped commands); the
        steps it closes."""
        jumped = self._jumped(stamp)
        self.cadence.add(stamp)
        last = self.stepper.last_image_time
        steps = []
        if last is None or stamp > last:  # else the stepper drops it: it dates nothing
            for date, (action, far) in self.dating.image(sent_ns, stamp):
                steps += self._command(date, action, far)
        steps += self.stepper.add_image(stamp, image)
        return Added(_steps(steps), jumped)

    def add_action(
        self, stamp: int | None, action: int, *, sent_ns: int = 0, far: bool = False
    ) -> Added:
        """A command in force from ``stamp`` on; ``stamp`` None (unstamped): from the first
        image sent after ``sent_ns``. The steps it closes."""
        if stamp is None:
            dated = self.dating.command(sent_ns, (action, far))
            if dated is None:
                return Added()
            stamp = dated[0]
        return Added(_steps(self._command(stamp, action, far)))

    def _command(self, stamp: int, action: int, far: bool) -> list[GridStep]:
        """A command put in force from ``stamp`` (counted as the bag's reading counts it)."""
        self.far_commands += int(far)
        return self.stepper.add_command(stamp, action)

    @property
    def command_messages(self) -> int:
        """Command messages put in force so far (the unit of ``far_commands``)."""
        return self.stepper.commands

    def flush(self) -> Added:
        """Close the steps before the newest image (both inputs fell silent)."""
        return Added(_steps(self.stepper.flush()))

    def episode_start(self, stamp: int) -> bool:
        """Robot streams have no episodes; a start message restarts the state."""
        return True

    def clock(self, stamp: int) -> bool:
        """``/clock``: a jump back restarts the grid."""
        return self._jumped(stamp)

    def counts(self) -> dict[str, int]:
        """Grid counters (images not newer than the last are dropped) and lost images."""
        stepper = self.stepper
        return {
            "dropped": stepper.images_out_of_order,
            "duplicates": 0,
            "late": stepper.late,
            "out_of_order": stepper.images_out_of_order,
            "time_jumps": self.time_jumps,
            "lost_images": self.lost_images,
            "lost_actions": 0,
            "camera_gaps": stepper.camera_gaps,
            "command_gaps": stepper.command_gaps,
            "far_commands": self.far_commands,
        }


class LockstepStepping:
    """One step per image of a lockstep robot (module docstring), on the model's grid.

    An image stamped ``s`` is the step at the first grid time at or after ``s`` (the grid
    step that takes it offline, as the next image comes at least a period later); its
    action is the node's last command sent (:meth:`command`). An image not newer than the
    previous one, or whose grid time was already stepped, is counted and dropped; an image
    before any command is a command gap.

    Stamps, not arrival order, decide where an episode starts: a start stamped ``t`` applies
    to the first image stamped after ``t``, whichever of the two arrives first. An image
    on the grid step right after the last one steps at once (a reset takes a stamp of its
    own, so no start lies between them); an image after a gap is held until the start
    before it arrives (:meth:`episode_start`, then :meth:`release` once the node has sent
    the command of the restarted state) or until the node gives up waiting (:meth:`flush`,
    after its lateness bound). ``/clock`` restarts the steps only when the clock's own time
    jumps back: its messages travel on another topic and may lag the images.
    """

    def __init__(self, grid: GridConfig, *, jump_threshold_ns: int) -> None:
        if grid.phase_ns is None:
            raise ConfigError(
                "lockstep needs a model whose step grid has a phase (refit it with learner fit)"
            )
        self.step_ns, self.phase_ns = int(grid.step_ns), int(grid.phase_ns)
        self.jump_threshold_ns = int(jump_threshold_ns)
        self.action: int | None = None
        self.last_image: int | None = None
        self.last_step: int | None = None
        self.last_clock: int | None = None
        self.start: int | None = None
        """Stamp of the newest episode start not yet followed by an image."""
        self.held: tuple[int, Any] | None = None
        """An image after a gap, waiting for the start before it (or the lateness bound)."""
        self.late = self.out_of_order = self.time_jumps = self.command_gaps = 0

    def step_time(self, stamp: int) -> int:
        """The first grid time at or after ``stamp``."""
        return int(stamp) + (self.phase_ns - int(stamp)) % self.step_ns

    def command(self, action: int) -> None:
        """The node sent ``action``: the robot's next step executes it."""
        self.action = int(action)

    def _restart(self) -> None:
        self.last_image = self.last_step = self.start = None
        self.held = None
        self.time_jumps += 1

    def _jumped(self, stamp: int) -> bool:
        if self.last_image is None or stamp >= self.last_image - self.jump_threshold_ns:
            return False
        self._restart()
        return True

    def add_image(self, stamp: int, image: Any) -> Added:
        """An image (any object holding it); the step it makes, if any (none while held)."""
        stamp = int(stamp)
        jumped = self._jumped(stamp)
        newest = self.last_image if self.held is None else self.held[0]
        if newest is not None and stamp <= newest:
            self.out_of_order += 1
            return Added(jumped=jumped, problem="late")
        released = self.flush().steps  # a newer image: the held one waited long enough
        at = self.step_time(stamp)
        first = self.start is not None and stamp > self.start
        if self.last_step is not None and at > self.last_step + self.step_ns and not first:
            self.held = (stamp, image)  # after a gap: an episode start may lie before it
            return Added(released, jumped)
        added = self._step(stamp, image)
        return Added(released + added.steps, jumped, added.problem)

    def _step(self, stamp: int, image: Any) -> Added:
        self.last_image, self.start = stamp, None
        at = self.step_time(stamp)
        if self.last_step is not None and at <= self.last_step:
            self.late += 1
            return Added(problem="late")
        if self.action is None:
            self.command_gaps += 1
            return Added()
        self.last_step = at
        return Added([Step(at, self.action, image)])

    def release(self) -> Added:
        """The held image if an episode start before it has arrived (call it once the
        restarted state's command is sent: that command is the image's action)."""
        if self.held is None or self.start is None or self.held[0] <= self.start:
            return Added()
        return self.flush()

    def flush(self) -> Added:
        """Step the held image now (the lateness bound expired: no start came before it)."""
        if self.held is None:
            return Added()
        (stamp, image), self.held = self.held, None
        return self._step(stamp, image)

    def episode_start(self, stamp: int) -> bool:
        """A start at ``stamp`` restarts the state unless an image after it was already
        stepped (then it is stale: its episode's steps were taken as one stream)."""
        stamp = int(stamp)
        if self.last_image is not None and stamp < self.last_image:
            if stamp >= self.last_image - self.jump_threshold_ns:
                return False
            self._restart()
        self.start = stamp
        return True

    def clock(self, stamp: int) -> bool:
        """``/clock``: a jump back of the clock's own time restarts the steps."""
        last, self.last_clock = self.last_clock, int(stamp)
        if last is None or stamp >= last - self.jump_threshold_ns:
            return False
        self._restart()
        return True

    def counts(self) -> dict[str, int]:
        """Counters in the grid's keys (dropped images are the out-of-order and late ones)."""
        return {
            "dropped": self.out_of_order + self.late,
            "duplicates": 0,
            "late": self.late,
            "out_of_order": self.out_of_order,
            "time_jumps": self.time_jumps,
            "lost_images": 0,
            "lost_actions": 0,
            "camera_gaps": 0,
            "command_gaps": self.command_gaps,
            "far_commands": 0,
        }


def _steps(closed: list[GridStep]) -> list[Step]:
    return [Step(s.stamp, int(s.command), s.image) for s in closed]
