"""On the closed-loop path a model archive is read once per process (ModelFile, handed along)."""

from __future__ import annotations

import pytest
from test_filter_node import fit_small_model, random_policy

from tpsr_ros.io import model_io


@pytest.fixture()
def reads(monkeypatch):
    """The paths of every model archive read from here on."""
    seen: list[str] = []
    original = model_io.read_archive

    def counting(path, *args, **kwargs):
        seen.append(str(path))
        return original(path, *args, **kwargs)

    monkeypatch.setattr(model_io, "read_archive", counting)
    return seen


def test_the_closed_loop_checks_read_the_model_once(tmp_path, reads):
    from learner.closed_loop import _check_inputs

    model = fit_small_model(tmp_path)
    policy = random_policy(model, tmp_path / "policy.npz")
    reads.clear()
    _check_inputs(policy, "full", model)  # learner closed-loop, before any process starts
    assert reads == [str(model)]


def test_the_filter_node_process_reads_the_model_once(tmp_path, reads, monkeypatch):
    """``python -m tpsr_ros.filter_node`` as run_node runs it: preflight, then the node."""
    from tpsr_ros.filter_node.node import FilterNode, main

    model = fit_small_model(tmp_path)
    policy = random_policy(model, tmp_path / "policy.npz")
    monkeypatch.setenv("TPSR_TRANSPORT", "inproc")
    started: list[FilterNode] = []

    def spin_once_then_stop(node: FilterNode, *args, **kwargs) -> bool:
        started.append(node)
        raise KeyboardInterrupt  # as a Ctrl-C right after start-up

    monkeypatch.setattr(FilterNode, "spin", spin_once_then_stop)
    reads.clear()
    with pytest.raises(SystemExit):
        main(["--ros-args", "-p", f"model:={model}", "-p", f"policy:={policy}"])
    assert started and started[0].policy is not None  # the node was built and set up
    assert reads == [str(model)]
