"""One refit of the learner node, free of ROS: steps in, model and policy files out.

The node hands a :class:`RefitRequest` (the first ``N`` live steps, pixels still uint8) to
a worker process, which runs :func:`refit` and returns a :class:`RefitResult`. The model
is :func:`tpsr_ros.core.refit.fit_trajectory` of those steps, so it equals ``learner fit
BAG`` (the first version, from the preset sized to the data) or ``learner fit BAG
--init-from LAST [--forgetting F]`` (every later one: ``LAST`` the version it replaces,
whose frozen basis, from the first version, it keeps) on a recording of the same steps.
With rewards among the steps the fitted-Q policy of the preset is fitted on the same
tracked states (``learner policy``'s planner).

A version's state coordinates are rotated to those of the model it replaces (the last
version, or ``init_model``: :mod:`tpsr_ros.core.alignment`), so the state a filter node
publishes does not jump at a swap. With ``forgetting`` below 1 a refit solves statistics
(:class:`~tpsr_ros.core.refit.SummedSteps`) in which every episode weighs
``forgetting ** age``: the request carries the last refit's, so only the steps since are
summed, and the policy is fitted on the last :func:`policy_horizon` steps only (under a
world that changes, the old steps' transitions would teach it the old world).

A frozen basis cannot follow a world that changes what the camera sees: its whitenings and
centres describe the first steps. A request with ``new_basis`` fits a new one, as ``learner
fit`` does, on the last :func:`policy_horizon` steps (every step without forgetting), rotated
to the model it replaces; the refits after it keep it and sum their statistics anew.
:class:`RefitChain` carries from each refit to the next what it continues (the last
version, its statistics, when its basis was fitted) for the node and ``learner
competence`` alike.

Files: every version is written to ``OUTPUT/versions/model-vNNNN.npz`` (and
``policy-vNNNN.npz``), then copied over ``OUTPUT/model.npz`` (and ``policy.npz``, which a
version without a policy removes, so the two never belong to different models); every
write is atomic (a temporary file and a rename), so a reader sees a whole file or the one
before. The announcement names the versioned files, which stay until ``keep`` newer
versions exist, so a filter node loading one is never raced by the next refit. A new run
into the same folder numbers its versions after the last one there and never removes an
earlier run's files.
"""

from __future__ import annotations

import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.core.errors import ConfigError, TpsrError
from tpsr_ros.core.presets import get_preset
from tpsr_ros.core.refit import SummedSteps, fit_trajectory
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr import TPSRModel
from tpsr_ros.io.atomic import atomic_file
from tpsr_ros.io.model_io import model_fingerprint, open_model, save_model
from tpsr_ros.io.policy import policy_from_states, save_policy
from tpsr_ros.io.trajectory import StepChunk

__all__ = [
    "RefitChain",
    "RefitRequest",
    "RefitResult",
    "last_version",
    "new_basis_due",
    "policy_horizon",
    "refit",
    "versioned",
]


@dataclass(frozen=True, eq=False)
class RefitRequest:
    """What one refit fits and where it writes.

    ``basis_model``: a model file whose basis (whitenings, centres, settings) the refit
    keeps; None: the first fit, from ``preset`` sized to the steps.
    """

    steps: StepChunk
    version: int
    output: Path
    preset: str
    basis_model: Path | None = None
    keep: int = 5
    first_version: int = 1
    """This run's first version: only its files are pruned."""
    reward_topic: str = ""
    forgetting: float = 1.0
    previous: SummedSteps | None = None
    """The statistics of the last refit of this run (None: sum every step)."""
    new_basis: bool = False
    """Fit a new basis on the last :func:`policy_horizon` steps instead of keeping
    ``basis_model``'s (whose state coordinates the new one's are rotated to)."""


@dataclass(frozen=True)
class RefitResult:
    """What a refit wrote, for the announcement and the node's diagnostics."""

    version: int
    steps: int
    model: Path
    fingerprint: str
    policy: Path | None
    fit_seconds: float
    total_seconds: float
    note: str = ""
    """Why no policy was written, when none was."""
    summed: SummedSteps | None = None
    """The statistics the model solves, for the next refit to continue (None: a first fit)."""
    policy_steps: int = 0
    """The last steps the policy was fitted on."""
    basis_steps: int = 0
    """The last steps this refit fitted a new basis on (0: it kept its model's)."""

    def update(self) -> dict[str, Any]:
        """The ``tpsr/model_update`` JSON object announcing this version."""
        update: dict[str, Any] = {
            "path": str(self.model),
            "fingerprint": self.fingerprint,
            "version": self.version,
            "steps": self.steps,
        }
        if self.policy is not None:
            update["policy"] = str(self.policy)
        return update


def policy_horizon(steps: int, forgetting: float) -> int:
    """The last steps a policy is fitted on: all without forgetting, else those weighing at
    least ``e^-3`` (5 %): ``3 / (1 - forgetting)`` steps."""
    if forgetting >= 1.0:
        return steps
    return min(steps, math.ceil(3.0 / (1.0 - forgetting)))


@dataclass
class RefitChain:
    """What each refit of a run continues from the one before, so that the learner node and
    ``learner competence`` make the same versions of the same steps.

    ``basis_model``: the last version (or ``init_model``), whose basis the next refit keeps
    and whose state coordinates it takes; ``summed``: its statistics, continued with
    forgetting; ``basis_at``: the steps when the basis in use was fitted (0: an
    ``init_model``'s; None: no basis yet).
    """

    forgetting: float = 1.0
    new_basis_steps: int = 0
    basis_model: Path | None = None
    summed: SummedSteps | None = None
    basis_at: int | None = None

    @classmethod
    def starting_from(
        cls, init_model: Path | None, *, forgetting: float = 1.0, new_basis_steps: int = 0
    ) -> RefitChain:
        """A run's chain: from ``init_model``'s basis, or (None) from a first fit."""
        return cls(forgetting, new_basis_steps, init_model, None, None if init_model is None else 0)

    def request(
        self, steps: StepChunk, version: int, output: Path, preset: str, **files: Any
    ) -> RefitRequest:
        """The next refit, of ``steps`` (``files``: :class:`RefitRequest`'s ``keep``,
        ``first_version`` and ``reward_topic``)."""
        new_basis = new_basis_due(len(steps.stamps), self.basis_at, self.new_basis_steps)
        return RefitRequest(
            steps, version, output, preset, basis_model=self.basis_model,
            forgetting=self.forgetting, previous=self.summed, new_basis=new_basis, **files,
        )  # fmt: skip

    def advance(self, result: RefitResult) -> None:
        """Continue from ``result``, the refit just written."""
        self.basis_model = result.model  # every version carries the basis it was fitted on
        self.summed = result.summed
        if result.basis_steps:
            self.basis_at = result.steps


def new_basis_due(steps: int, basis_at: int | None, every: int) -> bool:
    """Whether a refit of ``steps`` steps fits a new basis: ``every`` (> 0) or more steps
    after the refit that fitted the one in use at ``basis_at`` steps (None: no basis yet, the
    first fit makes one)."""
    return every > 0 and basis_at is not None and steps - basis_at >= every


def versioned(output: Path, kind: str, version: int) -> Path:
    """``OUTPUT/versions/<kind>-vNNNN.npz``."""
    return output / "versions" / f"{kind}-v{version:04d}.npz"


def refit(request: RefitRequest) -> RefitResult:
    """Fit the request's steps, write the model (and policy) files, say what was written."""
    start = time.perf_counter()
    trajectory = request.steps.trajectory()
    preset = get_preset(request.preset)
    environment = trajectory.summary()["environment"]
    turning = environment == "drive"
    basis, replaced = None, None  # the model this version replaces: basis, state coordinates
    fresh: dict[str, Any] = {"name": preset.name, "changed": {}}  # a first fit's preset
    if turning and preset.turning_tpsr:
        fresh["turning"] = True
    record = fresh
    live: dict[str, Any] = {"version": request.version}
    if request.basis_model is not None:
        opened = open_model(request.basis_model)
        replaced = opened.model if isinstance(opened.model, TPSRModel) else None
        basis = None if replaced is None else replaced.basis
        if basis is None:
            raise ConfigError(f"{request.basis_model} holds no fit basis to refit on")
        preset_record = opened.metadata.get("preset")
        record = preset_record if isinstance(preset_record, dict) else record
        live["init_from"] = {"path": str(request.basis_model), "fingerprint": opened.fingerprint}
    if request.forgetting != 1.0:
        live["forgetting"] = request.forgetting
    horizon = policy_horizon(len(trajectory), request.forgetting)
    recent = trajectory.rows(len(trajectory) - horizon, len(trajectory))
    fitted_steps = trajectory  # the steps the model is fitted on
    if request.new_basis:
        if replaced is None:
            raise ConfigError("a new basis replaces a model's: the request names none")
        basis, fitted_steps = None, recent
        record = fresh
        live["new_basis_steps"] = horizon
    fitted = fit_trajectory(
        fitted_steps, preset.tpsr_config(turning=turning), basis=basis, sizing=Sizing(),
        forgetting=request.forgetting if basis is not None else 1.0,
        previous=request.previous if basis is not None else None,
        align_to=replaced,
    )  # fmt: skip
    model = fitted.model
    fingerprint = model_fingerprint(model)
    output = Path(request.output)
    (output / "versions").mkdir(parents=True, exist_ok=True)
    model_path = versioned(output, "model", request.version)
    training = {**fitted.training(fitted_steps), "live": live}
    save_model(model, model_path, training=training, preset=record, view=fitted.view, force=True)
    policy_path, note = None, ""
    if np.isfinite(recent.rewards).any():
        try:
            policy = policy_from_states(
                fitted.tracked.states[len(fitted_steps) - horizon :],
                recent,
                preset.fqi_config(),
                representation=model.method,
                fingerprint=fingerprint,
                environment=environment if isinstance(environment, str) else None,
                metadata={
                    "model_path": str(model_path),
                    "preset": {"name": preset.name, "changed": {}},
                    "rewards": {"topic": request.reward_topic},
                },
                skip_unknown=True,
            )
        except TpsrError as exc:  # no usable transitions, or fitted Q diverged throughout
            note = f"no policy: {exc}"
        else:
            policy_path = versioned(output, "policy", request.version)
            save_policy(policy, policy_path, force=True)
    else:
        note = "no policy: no step has a reward" if horizon == len(trajectory) else (
            f"no policy: none of the last {horizon} steps has a reward"
        )  # fmt: skip
    _publish(model_path, output / "model.npz")
    if policy_path is not None:
        _publish(policy_path, output / "policy.npz")
    else:  # the last one was another model's (it stays in versions/ while kept)
        (output / "policy.npz").unlink(missing_ok=True)
    _prune(output, request.version, request.keep, request.first_version)
    return RefitResult(
        version=request.version,
        steps=len(trajectory),
        model=model_path,
        fingerprint=fingerprint,
        policy=policy_path,
        fit_seconds=fitted.seconds,
        total_seconds=time.perf_counter() - start,
        note=note,
        summed=fitted.summed,
        policy_steps=horizon if policy_path is not None else 0,
        basis_steps=len(fitted_steps) if basis is None else 0,
    )


def _publish(source: Path, target: Path) -> None:
    """Copy ``source`` over ``target`` atomically."""
    with source.open("rb") as src, atomic_file(target) as dst:
        shutil.copyfileobj(src, dst)


def _prune(output: Path, version: int, keep: int, first: int) -> None:
    """Remove this run's versioned files (from version ``first`` on) more than ``keep``
    versions old; an earlier run's stay."""
    for kind in ("model", "policy"):
        for old in range(first, version - keep + 1):
            versioned(output, kind, old).unlink(missing_ok=True)


def last_version(output: Path) -> int:
    """The highest version in ``OUTPUT/versions`` (0: none), so a new run numbers after it."""
    numbers = [0]
    for path in (output / "versions").glob("*-v*.npz"):
        number = path.stem.rpartition("-v")[2]
        if number.isdigit():
            numbers.append(int(number))
    return max(numbers)
