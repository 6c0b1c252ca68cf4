"""The learner node: live steps paired as a recording is read, versions equal to `learner fit`
(the first) and `learner fit --init-from` (the rest), announced, written atomically; bad
input counted and refused."""

from __future__ import annotations

import io
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
from cli_support import run_entry

from sim_node import SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.presets import PRESETS
from tpsr_ros.core.refit import fit_trajectory
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.model_io import model_fingerprint, open_model, save_model
from tpsr_ros.io.policy import load_policy
from tpsr_ros.io.trajectory import LiveSteps, read_trajectory
from tpsr_ros.learner_node import LearnerNode
from tpsr_ros.learner_node import node as learner_node
from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions, parse_ros_args
from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE, status_values
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

TOPICS = {
    "/camera/image_raw": m.IMAGE_TYPE,
    "/action": m.ACTION_TYPE,
    "/ground_truth/pose": m.POSE_TYPE,
    "/reward": m.REWARD_TYPE,
}
STEPS, WARMUP, REFIT = 1200, 600, 200
NEW_BASIS = 400
"""The ``learned`` node's new_basis_steps: version 3 (1000 steps) fits a new basis."""
IDLE = 2.0
"""The harness waits for each refit between steps: the streams' pause must not close a step."""


WORKER_NICENESS = learner_node.WORKER_NICENESS


@pytest.fixture(scope="module", autouse=True)
def refits_at_the_tests_priority():
    """The harness waits for every refit, so its worker runs at this process's priority here:
    at niceness 19 it waits for idle cores, and beside the other test workers' tests a refit
    of 1 s CPU took up to a minute. The node's own niceness is checked by
    test_the_refit_worker_runs_at_the_lowest_priority_with_one_blas_thread."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(learner_node, "WORKER_NICENESS", 0)
        yield


def test_the_refit_worker_runs_at_the_lowest_priority_with_one_blas_thread(monkeypatch):
    monkeypatch.setattr(learner_node, "WORKER_NICENESS", WORKER_NICENESS)
    for variable in learner_node.BLAS_THREADS:
        monkeypatch.setenv(variable, "4")  # the node's own environment: not the worker's
    pool = learner_node._worker()
    try:
        pid = pool.submit(os.getpid).result(timeout=60)
        niceness = os.getpriority(os.PRIO_PROCESS, pid)  # while the worker is up
        threads = [pool.submit(os.getenv, v).result(timeout=60) for v in learner_node.BLAS_THREADS]
    finally:
        pool.shutdown()
    assert WORKER_NICENESS == 19
    assert niceness == min(19, os.getpriority(os.PRIO_PROCESS, 0) + 19)
    assert threads == ["1", "1", "1"] and os.environ["OPENBLAS_NUM_THREADS"] == "4"


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("learner_node") / "run"
    generate_bag(path, SimConfig(environment="full"), STEPS, seed=8)
    return path


def _messages(bag: Path) -> list[tuple[str, bytes]]:
    with BagReader(bag) as reader:
        return [(topic, data) for topic, _, data in reader.raw_messages(list(TOPICS))]


class Harness:
    """A learner node on the in-process bus, a feeder of raw messages, a probe of updates."""

    def __init__(self, output: Path, *params: str) -> None:
        self.bus = InprocBus()
        self.feeder = Node(NodeOptions(name="feeder"), transport=InprocTransport("/f", self.bus))
        self.pubs = {t: self.feeder.create_publisher(t, ty) for t, ty in TOPICS.items()}
        self.pubs_update = self.feeder.create_publisher(
            "/tpsr/model_update", "std_msgs/msg/String", LATCHED_QOS
        )
        self.also_spin: Node | None = None  # another node on the bus (a filter node)
        self.updates: list[dict] = []
        self.diagnostics: list = []
        self.levels: list[int] = []  # of every /diagnostics report
        self.feeder.create_subscription(
            "/tpsr/model_update", "std_msgs/msg/String",
            self._on_update, LATCHED_QOS,
        )  # fmt: skip
        self.feeder.create_subscription(
            "/diagnostics", DIAGNOSTICS_TYPE, self._on_diagnostics
        )
        args = ["-p", f"output:={output}", "-p", f"warmup_steps:={WARMUP}",
                "-p", f"refit_steps:={REFIT}", "-p", "environment:=full",
                "-p", "diagnostics_period:=0.05", "-p", f"idle_flush:={IDLE}"]  # fmt: skip
        for p in params:
            args += ["-p", p]
        options = NodeOptions.for_node(LearnerNode, parse_ros_args(args))
        self.node = LearnerNode(options, transport=InprocTransport("/tpsr_learner", self.bus))
        self.log = io.StringIO()
        self.node.logger.stream = self.log

    def _on_update(self, msg) -> None:
        update = json.loads(msg.data)
        if "version" in update:  # the learner node's, not the test's own
            self.updates.append(update)

    def _on_diagnostics(self, msg) -> None:
        self.diagnostics.append(msg)
        self.levels.append(int(msg.status[0].level))

    def feed(self, messages: list[tuple[str, bytes]], wait_for: int | None = None) -> None:
        """Publish the messages; with ``wait_for``, spin until that many versions arrived."""
        for topic, data in messages:
            if wait_for is not None and topic == "/camera/image_raw":
                while self.node.job is not None:  # one refit at a time, as at a calm rate
                    self.spin(0.02)
            self.pubs[topic].publish_raw(data)
            self.node.spin_once(0.0)
            if self.also_spin is not None:
                self.also_spin.spin_once(0.0)
                self.feeder.spin_once(0.0)
        deadline = time.monotonic() + 120
        while wait_for is not None and len(self.updates) < wait_for:
            assert time.monotonic() < deadline, self.log.getvalue()
            self.spin(0.02)

    def spin(self, timeout: float) -> None:
        self.node.spin_once(timeout)
        if self.also_spin is not None:
            self.also_spin.spin_once(0.0)
        self.feeder.spin_once(0.0)

    def values(self) -> dict:
        self.diagnostics.clear()
        while not self.diagnostics:
            self.spin(0.02)
        return status_values(self.diagnostics[-1].status[0])

    def close(self) -> None:
        self.node.close()
        self.feeder.close()


@pytest.fixture(scope="module")
def learned(bag, tmp_path_factory):
    """Every message of the bag fed to a learner node: its versions and its output folder."""
    output = tmp_path_factory.mktemp("learned") / "out"
    h = Harness(output, f"new_basis_steps:={NEW_BASIS}")
    try:
        h.feed(_messages(bag), wait_for=1 + (STEPS - WARMUP) // REFIT)
        values = h.values()
    finally:
        h.close()
    return {"output": output, "updates": h.updates, "values": values, "log": h.log.getvalue()}


def test_live_steps_are_the_steps_read_from_a_recording(bag):
    got, expected = LiveSteps.of_bag(bag, "full").trajectory(), read_trajectory([bag])
    for name in ("stamps", "observations", "actions", "velocities", "positions", "rewards",
                 "segments"):  # fmt: skip
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), name)


@pytest.mark.slow
def test_a_version_at_every_due_point_announced_with_its_files(learned):
    updates = learned["updates"]
    assert [u["version"] for u in updates] == [1, 2, 3, 4]
    assert [u["steps"] for u in updates] == [600, 800, 1000, 1200]
    for update in updates:
        model = open_model(update["path"])
        assert model.fingerprint == update["fingerprint"]
        assert load_policy(update["policy"]).model_fingerprint == update["fingerprint"]
    output = learned["output"]
    assert open_model(output / "model.npz").fingerprint == updates[-1]["fingerprint"]
    assert load_policy(output / "policy.npz").model_fingerprint == updates[-1]["fingerprint"]
    values = learned["values"]
    assert values["versions_written"] == "4" and values["steps"] == str(STEPS)
    assert values["refits_failed"] == "0" and values["rejected_late"] == "0"


@pytest.mark.slow
def test_the_first_version_is_learner_fit_of_its_steps(bag, learned):
    steps = read_trajectory([bag]).rows(0, WARMUP)
    config = PRESETS["best"].tpsr_config()
    expected = fit_trajectory(steps, config, sizing=Sizing()).model
    first = open_model(learned["updates"][0]["path"])
    assert first.fingerprint == model_fingerprint(expected)
    assert first.model.basis is not None


@pytest.mark.slow
def test_the_last_version_is_learner_fit_init_from_on_a_recording(bag, learned, tmp_path, capsys):
    """The last version refits on the basis of the one it replaces, in its coordinates."""
    replaced, last = learned["updates"][-2], learned["updates"][-1]
    out = tmp_path / "offline.npz"
    code, _, stderr = run_entry(
        ["fit", str(bag), "--init-from", replaced["path"], "-o", str(out)], capsys
    )
    assert code == 0, stderr
    offline, live = open_model(out).model, open_model(last["path"]).model
    for name, array in offline.to_arrays().items():
        np.testing.assert_allclose(live.to_arrays()[name], array, rtol=0, atol=1e-9)
    assert open_model(last["path"]).training["live"]["init_from"]["fingerprint"] is not None


@pytest.mark.slow
def test_a_new_basis_is_learner_fit_of_its_steps_in_the_coordinates_before(bag, learned):
    """Version 3, 400 steps after the first's basis, fits a new one as ``learner fit`` does on
    its 1000 steps, rotated to version 2's states; version 4 keeps it."""
    _, second, third, fourth = (open_model(u["path"]) for u in learned["updates"])
    steps = read_trajectory([bag]).rows(0, 1000)
    expected = fit_trajectory(
        steps, PRESETS["best"].tpsr_config(), sizing=Sizing(), align_to=second.model
    ).model
    assert "skipped" not in expected.fit_info["aligned"]  # rotated: the same rank
    for name, array in expected.to_arrays().items():
        np.testing.assert_allclose(third.model.to_arrays()[name], array, rtol=0, atol=1e-9)
    assert third.training["live"]["new_basis_steps"] == 1000
    assert "new_basis_steps" not in fourth.training["live"]
    bases = [m.model.basis for m in (second, third, fourth)]
    assert not np.array_equal(bases[0].obs.components_, bases[1].obs.components_)
    np.testing.assert_array_equal(bases[1].obs.components_, bases[2].obs.components_)
    assert learned["values"]["basis_fitted_at_steps"] == "1000"


@pytest.mark.slow
def test_old_versions_of_the_run_are_pruned_and_an_earlier_runs_kept(bag, tmp_path):
    output = tmp_path / "out"
    (output / "versions").mkdir(parents=True)
    earlier = output / "versions" / "model-v0007.npz"
    earlier.write_bytes(b"an earlier run's model")
    h = Harness(output, "keep_versions:=1")
    try:
        h.feed(_messages(bag)[: 4 * (WARMUP + 2 * REFIT + 11)], wait_for=3)
    finally:
        h.close()
    assert [u["version"] for u in h.updates] == [8, 9, 10]
    names = sorted(p.name for p in (output / "versions").glob("model-*.npz"))
    assert names == ["model-v0007.npz", "model-v0010.npz"]
    assert earlier.read_bytes() == b"an earlier run's model"


@pytest.mark.slow
def test_bad_messages_are_counted_and_the_node_keeps_learning(bag, tmp_path):
    messages = _messages(bag)[: 4 * (WARMUP + 5)]
    image = next(data for topic, data in messages if topic == "/camera/image_raw")
    h = Harness(tmp_path / "out")
    try:
        h.feed([("/camera/image_raw", image[:40]), ("/camera/image_raw", image)])
        h.feed(messages, wait_for=1)
        values = h.values()
    finally:
        h.close()
    assert values["rejected_undecodable"] == "1"
    assert values["rejected_repeated"] == "1"  # the first image came twice
    assert "/camera/image_raw: " in h.log.getvalue()
    assert 1 in h.levels  # WARN while messages are rejected
    assert len(h.updates) == 1


@pytest.mark.slow
def test_a_refit_that_fails_is_reported_and_retried_with_more_steps(bag, tmp_path):
    messages = _messages(bag)
    h = Harness(tmp_path / "out", "warmup_steps:=4", "refit_steps:=800")
    try:
        h.feed(messages[:8])  # the first two steps' messages
        h.feed(messages[8:20])  # four steps: the warm-up's refit runs and fails
        while h.node.failures == 0:
            h.spin(0.02)
        h.values()
        h.feed(messages[20 : 4 * 820], wait_for=1)
        values = h.values()
    finally:
        h.close()
    assert values["refits_failed"] == "1" and "refit of 4 steps failed" in h.log.getvalue()
    assert 2 in h.levels and h.levels[-1] == 0  # ERROR until a refit succeeds again
    assert [u["steps"] for u in h.updates] == [804]  # the next due point, with more steps


def test_an_init_model_without_a_basis_or_for_a_robot_is_refused(bag, tmp_path):
    from dataclasses import replace

    from tpsr_ros.core.learn import fit

    model = fit(read_trajectory([bag]))
    old = save_model(replace(model, basis=None), tmp_path / "old.npz")
    options = NodeOptions.for_node(
        LearnerNode, parse_ros_args(["-p", f"output:={tmp_path}", "-p", f"init_model:={old}"])
    )
    with pytest.raises(ConfigError, match="holds no fit basis"):
        LearnerNode.preflight(options)
    file = tmp_path / "a_file"
    file.write_text("")
    options = NodeOptions.for_node(LearnerNode, parse_ros_args(["-p", f"output:={file}"]))
    with pytest.raises(ConfigError, match="is not a folder"):
        LearnerNode.preflight(options)
    with pytest.raises(ConfigError, match="no output folder"):
        LearnerNode.preflight(NodeOptions.for_node(LearnerNode, parse_ros_args([])))


@pytest.mark.slow
def test_an_init_models_basis_is_kept_from_the_first_version(bag, tmp_path, capsys):
    start = save_model(fit_trajectory(read_trajectory([bag]).rows(0, 900),
                                      PRESETS["best"].tpsr_config(), sizing=Sizing()).model,
                       tmp_path / "start.npz")  # fmt: skip
    h = Harness(tmp_path / "out", f"init_model:={start}")
    try:
        h.feed(_messages(bag)[: 4 * (WARMUP + 20)], wait_for=1)
    finally:
        h.close()
    first = open_model(h.updates[0]["path"])
    np.testing.assert_array_equal(first.model.obs_centers, open_model(start).model.obs_centers)
    assert first.training["live"]["init_from"]["path"] == str(start)


@pytest.mark.slow
def test_a_filter_node_waits_for_the_first_version_and_swaps_in_the_rest(bag, tmp_path):
    from tpsr_ros.filter_node import FilterNode
    from tpsr_ros.filter_node.swap import string_msg

    h = Harness(tmp_path / "out")
    options = NodeOptions.for_node(
        FilterNode, parse_ros_args(["-p", "wait_for_model:=true", "-p", "view:=false"])
    )
    filter_node = FilterNode(options, transport=InprocTransport("/tpsr_filter", h.bus))
    filter_node.logger.stream = h.log
    states: list[int] = []
    infos: list[dict] = []
    h.feeder.create_subscription("/tpsr/state", m.STATE_TYPE,
                                 lambda msg: states.append(m.stamp_of(msg)))  # fmt: skip
    h.feeder.create_subscription(
        "/tpsr/model_info", "std_msgs/msg/String",
        lambda msg: infos.append(json.loads(msg.data)), LATCHED_QOS,
    )  # fmt: skip
    h.also_spin = filter_node
    messages = _messages(bag)
    cut = 4 * 1050  # the messages of the first 1050 steps: three versions
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK not a model")
    try:
        h.feed(messages[:cut], wait_for=3)
        h.pubs_update.publish(string_msg(json.dumps({"path": str(corrupt)})))
        h.spin(0.05)
        refused_at = states[-1]
        h.feed(messages[cut:], wait_for=4)
        for _ in range(5):
            h.spin(0.02)
        values = filter_node.diagnostics_values()
    finally:
        filter_node.close()
        h.close()
    assert [i["version"] for i in infos if i["first_stamp_ns"] is None] == [1, 2, 3, 4]
    assert infos[-1]["fingerprint"] == h.updates[-1]["fingerprint"]
    assert values["model_swaps"] == 3 and values["model_swaps_refused"] == 1
    assert "corrupt.npz refused" in h.log.getvalue()
    step = 10**9
    assert np.all(np.diff(states) == step)  # from the first version on, no step missed
    assert states[-1] == STEPS * step and refused_at < states[-1]


@pytest.mark.slow
def test_a_worker_that_dies_is_replaced_and_the_next_refit_runs(bag, tmp_path):
    messages = _messages(bag)
    h = Harness(tmp_path / "out")
    try:
        fed = 0
        while h.node.job is None:  # until the warm-up's steps are final and its refit starts
            h.feed(messages[fed : fed + 1])
            fed += 1
        for process in list(h.node.worker._processes.values()):
            process.kill()  # as the kernel's out-of-memory killer would
        while h.node.failures == 0:
            h.spin(0.02)
        h.feed(messages[fed : 4 * (WARMUP + REFIT + 11)], wait_for=1)
    finally:
        h.close()
    assert "BrokenProcessPool" in h.log.getvalue()
    assert h.updates[0]["steps"] == WARMUP + REFIT and h.updates[0]["version"] == 1
