"""The learner node: learns the TPSR and its policy from live streams, and announces each version.

    python -m tpsr_ros.learner_node --ros-args -p output:=DIR [-p warmup_steps:=1000]
        [-p refit_steps:=1000] [-p environment:=full] [-p init_model:=MODEL]

It subscribes the simulator's camera, action, pose and reward topics (raw CDR) and makes
steps of them exactly as ``learner fit`` reads a recording of them
(:class:`~tpsr_ros.io.trajectory.LiveSteps`). After ``warmup_steps`` steps, then every
``refit_steps`` more, a worker process refits on the steps so far
(:mod:`~tpsr_ros.learner_node.refits`): the first version fits the preset sized to the
warm-up (or, with ``init_model``, keeps that model's whitenings and centres), every later
one keeps the first's and takes the state coordinates of the one before (with
``forgetting`` below 1 older steps weigh less, and a refit continues the last one's
statistics: only the steps since are summed), so version ``n`` is ``learner fit BAG
--init-from PREVIOUS [--forgetting F]`` on a recording of its steps. With
``new_basis_steps`` N, the first refit N steps after the basis in use was fitted fits a new
one on its last steps, as ``learner fit`` does, in the coordinates of the one before. Each
version is written atomically to ``DIR`` and announced on the latched ``tpsr/model_update``
(JSON: path, fingerprint, version, steps, policy), which the filter node swaps in at a step
boundary. The subscriptions never wait for a refit: it runs in another process, and the
node only hands it the steps and reads its answer.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tpsr_ros.core.episodes import DEFAULT_IMAGE_SHAPE
from tpsr_ros.core.errors import ConfigError, MessageError, TpsrError
from tpsr_ros.core.presets import PRESETS
from tpsr_ros.core.tpsr import TPSRModel
from tpsr_ros.filter_node.health import Throttle
from tpsr_ros.filter_node.params import DIAGNOSTICS_TOPIC, MODEL_UPDATE_TOPIC
from tpsr_ros.filter_node.swap import MODEL_MESSAGE_TYPE, string_msg
from tpsr_ros.io import messages as m
from tpsr_ros.io.filter_inputs import model_image_shape
from tpsr_ros.io.model_io import ModelFile, open_model
from tpsr_ros.io.trajectory import LateMessage, LiveSteps, RepeatedMessage, Topics
from tpsr_ros.learner_node.refits import RefitChain, RefitResult, last_version, refit
from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions, param, run_node
from tpsr_ros.runtime.diagnostics import (
    DIAGNOSTICS_TYPE,
    ERROR,
    OK,
    WARN,
    diagnostic_array,
    diagnostic_status,
)
from tpsr_ros.runtime.launcher import environ_overrides

__all__ = ["PROG", "LearnerNode", "LearnerNodeParams", "main"]

PROG = "python -m tpsr_ros.learner_node"
TOPICS = {
    LiveSteps.IMAGE: ("camera/image_raw", m.IMAGE_TYPE),
    LiveSteps.ACTION: ("action", m.ACTION_TYPE),
    LiveSteps.POSE: ("ground_truth/pose", m.POSE_TYPE),
    LiveSteps.REWARD: ("reward", m.REWARD_TYPE),
}
"""The simulator's topics the node learns from, by kind (relative: they follow the namespace)."""
REFIT_SERVICE = "~/refit"
"""The ``std_srvs/srv/Trigger`` service that refits on the steps so far (rclpy only)."""
WORKER_NICENESS = 19
"""How much lower the refit worker's scheduling priority is than the node's."""
BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""The BLAS libraries' thread-count variables, set to 1 for the refit worker."""
POLL_S = 0.05
"""Seconds between looks at the refit in progress and at the streams' silence."""
WARN_PERIOD_S = 5.0
"""At most one warning per topic and kind in this many seconds."""
LIVE_PRESET = "best"
"""The preset of the node's refits unless ``preset`` names another: the one its time to
competence was measured with (docs/results.md). The default of the offline commands,
``predictive``, refines every fit through its filter (about four times the fit's time) and
its refits on a kept basis, with forgetting, are not yet measured."""


@dataclass(frozen=True)
class LearnerNodeParams:
    """Parameters of ``python -m tpsr_ros.learner_node``."""

    output: str = param(
        "", "folder of the models: model.npz, policy.npz and versions/ (required; created)"
    )
    warmup_steps: int = param(
        1000, "steps of the first fit, whose whitenings and kernel centres every refit keeps",
        minimum=2,
    )  # fmt: skip
    refit_steps: int = param(1000, "steps between refits after the first", minimum=1)
    init_model: str = param(
        "", "a model whose whitenings, centres and settings to keep from the first version "
        "on (empty: fit them on the warm-up steps with the preset)",
    )  # fmt: skip
    preset: str = param(
        LIVE_PRESET, "named fit and fitted-Q settings of the first fit and of every policy",
        choices=tuple(sorted(PRESETS)),
    )  # fmt: skip
    environment: str = param(
        "", "the simulator environment of the streams, recorded in the models (drive: its 9 "
        "actions and heading; empty: unknown, the planar environments' 25 actions)",
    )  # fmt: skip
    reorder_window: int = param(
        10, "later stamps a message may trail its step's and still join it", minimum=1
    )
    idle_flush: float = param(
        0.5, "s without a message after which the steps waiting for late messages are final",
        positive=True,
    )  # fmt: skip
    forgetting: float = param(
        1.0, "weight of a step one step older in every refit after the first, in (0, 1] "
        "(1: every step alike; 0.9995: a step 1386 steps old weighs half); the policy is "
        "fitted on the last 3 / (1 - forgetting) steps",
    )  # fmt: skip
    new_basis_steps: int = param(
        0, "steps after which a refit fits new whitenings and kernel centres on the last 3 / "
        "(1 - forgetting) steps (every step without forgetting), rotated to the version it "
        "replaces; the refits after it keep them (0: every refit keeps the first's)",
        minimum=0,
    )  # fmt: skip
    keep_versions: int = param(
        5, "versioned files of this run kept in output/versions (older ones are removed)",
        minimum=1,
    )  # fmt: skip
    diagnostics_period: float = param(1.0, "s between /diagnostics reports", positive=True)


class LearnerNode(Node):
    """Refits the TPSR and its policy on live steps; announces each version."""

    default_name = "tpsr_learner"
    Params = LearnerNodeParams
    description = (
        "Learn the TPSR and its fitted-Q policy from live streams: refit every refit_steps "
        "steps and announce each version on tpsr/model_update."
    )

    @classmethod
    def preflight(cls, options: NodeOptions) -> ModelFile | None:
        """Check the output folder and open the initial model before joining the graph."""
        p: LearnerNodeParams = options.params
        if not p.output:
            raise ConfigError("no output folder given: pass -p output:=DIR")
        output = Path(p.output)
        if output.exists() and not output.is_dir():
            raise ConfigError(f"output {p.output} exists and is not a folder")
        if not 0.0 < p.forgetting <= 1.0:
            raise ConfigError(f"forgetting must lie in (0, 1], not {p.forgetting}")
        if not p.init_model:
            return None
        init = open_model(p.init_model)
        if not isinstance(init.model, TPSRModel) or init.model.basis is None:
            raise ConfigError(
                f"init_model {p.init_model} holds no fit basis (a PCA model, or a TPSR written "
                "before models kept their whitenings and centres): fit it again with `learner fit`"
            )
        if init.spec is not None:
            raise ConfigError(
                f"init_model {p.init_model} reads a robot's streams on a step grid; the "
                "learner node learns from the simulator's stamped topics"
            )
        return init

    def setup(self) -> None:
        """Create the output folder, the subscriptions, the announcement and the worker."""
        p: LearnerNodeParams = self.params
        prepared = self.prepared
        init = prepared if isinstance(prepared, ModelFile) else self.preflight(self.options)
        self.output = Path(p.output)
        self.output.mkdir(parents=True, exist_ok=True)
        names = {kind: self.resolve_topic(name) for kind, (name, _) in TOPICS.items()}
        image_shape = DEFAULT_IMAGE_SHAPE if init is None else model_image_shape(init)
        environment = p.environment or (init.environment if init is not None else None)
        self.live = LiveSteps(
            environment or None, image_shape=image_shape, window=p.reorder_window,
            topics=Topics(
                image=names[LiveSteps.IMAGE], action=names[LiveSteps.ACTION],
                pose=names[LiveSteps.POSE], reward=names[LiveSteps.REWARD],
            ),
        )  # fmt: skip
        self.chain = RefitChain.starting_from(
            None if init is None else init.path,
            forgetting=p.forgetting, new_basis_steps=p.new_basis_steps,
        )  # fmt: skip
        self.first_version = last_version(self.output) + 1
        self.version = self.first_version - 1
        self.next_due = p.warmup_steps
        self.job: Future[RefitResult] | None = None
        self.job_steps = 0
        self.last_result: RefitResult | None = None
        self.failures = 0
        self.last_error = ""  # of the last refit, when it failed
        self.rejected: dict[str, int] = {"undecodable": 0, "late": 0, "repeated": 0}
        self._throttle = Throttle(WARN_PERIOD_S)
        self._last_message = time.monotonic()
        for kind, (name, msgtype) in TOPICS.items():
            self.create_subscription(name, msgtype, self._receiver(kind, names[kind]), raw=True)
        self.update_pub = self.create_publisher(
            MODEL_UPDATE_TOPIC, MODEL_MESSAGE_TYPE, LATCHED_QOS
        )
        self.diagnostics_pub = self.create_publisher(DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE)
        self.refit_service = self.create_trigger_service(REFIT_SERVICE, self.refit_now)
        self.worker = _worker()
        self.create_timer(POLL_S, self._poll)
        self.create_timer(p.diagnostics_period, self.publish_diagnostics)
        start = "the preset " + p.preset if init is None else f"the basis of {p.init_model}"
        self.logger.info(
            f"learning from {', '.join(names.values())}: first fit after {p.warmup_steps} "
            f"steps ({start}), then every {p.refit_steps}; versions in {self.output} from "
            f"v{self.first_version}, announced on {self.update_pub.topic}"
        )

    # -- steps ----------------------------------------------------------------------------

    def _receiver(self, kind: int, topic: str) -> Any:
        def on_message(data: bytes) -> None:
            self._last_message = time.monotonic()
            try:
                self.live.add(kind, data)
            except MessageError as exc:
                self._reject(topic, "undecodable", str(exc))
            except LateMessage as exc:
                self._reject(topic, "late", f"a message of stamp {exc} ns came after its step "
                             "was closed and is dropped (raise reorder_window or idle_flush if "
                             "messages trail further)")
            except RepeatedMessage as exc:
                self._reject(topic, "repeated", f"a second message with stamp {exc} ns ignored")
            self._start_refit()

        return on_message

    def _reject(self, topic: str, reason: str, detail: str) -> None:
        self.rejected[reason] += 1
        if (text := self._throttle.warning((topic, reason), f"{topic}: {detail}")) is not None:
            self.logger.warning(text)

    def _poll(self) -> None:
        """Collect a finished refit; make waiting steps final once the streams pause."""
        if self.job is not None and self.job.done():
            self._finish(self.job)
        idle = time.monotonic() - self._last_message
        if self.live.pairing.pending and idle >= self.params.idle_flush:
            self.live.flush()
        self._start_refit()

    # -- refits ---------------------------------------------------------------------------

    def refit_now(self) -> tuple[bool, str]:
        """``~/refit`` (``std_srvs/srv/Trigger``): refit on every step so far, now."""
        if self.job is not None:
            return False, f"a refit of {self.job_steps} steps is running; ask again after it"
        if len(self.live) < 2:
            return False, f"{len(self.live)} steps so far: too few to fit"
        self._submit(len(self.live))
        return True, f"refit of {self.job_steps} steps started (v{self.version + 1})"

    def _start_refit(self) -> None:
        """Hand the steps to the worker when a refit is due and none is running."""
        if self.job is not None or len(self.live) < self.next_due:
            return
        step = self.params.refit_steps
        while len(self.live) >= self.next_due + step:  # behind: the latest due point only
            self.next_due += step
        self._submit(self.next_due)

    def _submit(self, steps: int) -> None:
        """Refit on the first ``steps`` steps in the worker."""
        self.job_steps = steps
        request = self.chain.request(
            self.live.chunk(steps), self.version + 1, self.output, self.params.preset,
            keep=self.params.keep_versions, first_version=self.first_version,
            reward_topic=self.live.topics.reward,
        )  # fmt: skip
        self.job = self.worker.submit(refit, request)

    def _finish(self, job: Future[RefitResult]) -> None:
        self.job = None
        self.next_due = self.job_steps + self.params.refit_steps
        try:
            result = job.result()
        except Exception as exc:  # noqa: BLE001 - any failure of a refit leaves the node running
            restarted = ""
            if isinstance(exc, BrokenProcessPool):  # the worker died (out of memory?): anew
                self.worker, restarted = _worker(), " (a new worker process is started)"
            self.failures += 1
            self.last_error = (
                str(exc) if isinstance(exc, TpsrError) else f"{type(exc).__name__}: {exc}"
            )
            self.logger.error(
                f"the refit of {self.job_steps} steps failed: {self.last_error}{restarted}; "
                f"the next is due at {self.next_due} steps"
            )
            return
        self.last_error = ""
        self.version = result.version
        self.chain.advance(result)
        self.last_result = result
        self.update_pub.publish(string_msg(json.dumps(result.update(), sort_keys=True)))
        policy = f", policy {result.policy.name}" if result.policy is not None else ""
        note = f" ({result.note})" if result.note else ""
        self.logger.info(
            f"v{result.version}: {result.steps} steps, model {result.fingerprint[:12]}"
            f"{policy}{note}; fit {result.fit_seconds:.2f} s, refit {result.total_seconds:.2f} s"
        )

    # -- health ---------------------------------------------------------------------------

    def diagnostics_values(self) -> dict[str, Any]:
        """What ``/diagnostics`` reports."""
        last, basis_at = self.last_result, self.chain.basis_at
        return {
            "steps": len(self.live),
            "steps_waiting_for_pairing": self.live.pairing.pending,
            "unpaired_stamps": self.live.unpaired,
            **{f"rejected_{reason}": n for reason, n in self.rejected.items()},
            "versions_written": 0 if last is None else last.version - self.first_version + 1,
            "version": "none" if last is None else last.version,
            "refit_running": self.job is not None,
            "next_refit_at_steps": self.next_due,
            "refits_failed": self.failures,
            "last_refit_s": "none" if last is None else last.total_seconds,
            "last_fit_s": "none" if last is None else last.fit_seconds,
            "forgetting": self.params.forgetting,
            "last_policy_steps": "none" if last is None else last.policy_steps,
            "new_basis_steps": self.params.new_basis_steps,
            "basis_fitted_at_steps": "none" if basis_at is None else basis_at,
        }

    def publish_diagnostics(self) -> None:
        """Publish one DiagnosticArray (timer callback)."""
        values = self.diagnostics_values()
        if self.last_error:
            level, message = ERROR, f"the last refit failed: {self.last_error}"
        elif any(self.rejected.values()):
            level, message = WARN, "messages rejected (see the counts)"
        else:
            level, message = OK, "learning"
        status = diagnostic_status(
            level, f"{self.name}: learning", message, values, hardware_id="tpsr"
        )
        self.diagnostics_pub.publish(diagnostic_array(self.now_ns(), [status]))

    def on_shutdown(self) -> None:
        """Let a running refit finish its files (each write is atomic), then stop the worker."""
        self.worker.shutdown(wait=True, cancel_futures=True)


def _worker() -> ProcessPoolExecutor:
    """One worker process for the refits, started now: spawned, so it starts clean of the
    middleware's threads and sockets; at a lower priority (niceness
    :data:`WORKER_NICENESS`) and with one BLAS thread, so the nodes beside it (the filter
    node's steps) go first on the robot's cores."""
    pool = ProcessPoolExecutor(
        1, mp_context=multiprocessing.get_context("spawn"),
        initializer=os.nice, initargs=(WORKER_NICENESS,),
    )  # fmt: skip
    with environ_overrides(dict.fromkeys(BLAS_THREADS, "1")):  # read by the child as it starts
        pool.submit(os.getpid)  # spawns the process here, with this environment
    return pool


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m tpsr_ros.learner_node``."""
    run_node(LearnerNode, prog=PROG, argv=argv)
