"""Policy files: round trip, the model they name, and refusals."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from tpsr_ros.core.errors import ModelFormatError
from tpsr_ros.core.fqi import FQIConfig, fit_q
from tpsr_ros.io.npz_archive import write_archive
from tpsr_ros.io.policy import Policy, load_policy, save_policy


@pytest.fixture(scope="module")
def policy():
    rng = np.random.default_rng(0)
    s = rng.normal(size=(800, 3))
    q = fit_q(s, rng.integers(0, 4, 800), rng.normal(size=800), s, 4, FQIConfig(centers=10))
    return Policy(q, "tpsr", "f" * 64, "partial", {"fqi": {"centers": 10}})


def test_round_trip_is_exact(tmp_path, policy):
    path = save_policy(policy, tmp_path / "p.npz")
    loaded = load_policy(path)
    assert loaded.representation == "tpsr" and loaded.model_fingerprint == "f" * 64
    assert loaded.environment == "partial" and loaded.metadata["fqi"] == {"centers": 10}
    states = np.random.default_rng(1).normal(size=(50, 3))
    assert np.array_equal(loaded.q.values(states), policy.q.values(states))
    assert [loaded.action(x) for x in states] == [policy.action(x) for x in states]


def test_an_ensemble_over_whitened_states_round_trips(tmp_path):
    rng = np.random.default_rng(2)
    s = rng.normal(size=(800, 3)) @ rng.normal(size=(3, 3))
    config = FQIConfig(centers=10, ensemble=3, state_scaling="whiten")
    q = fit_q(s, rng.integers(0, 4, 800), rng.normal(size=800), s, 4, config)
    loaded = load_policy(save_policy(Policy(q, "tpsr", "f" * 64), tmp_path / "e.npz")).q
    assert loaded.members == 3 and np.array_equal(loaded.group_sizes, q.group_sizes)
    assert np.array_equal(loaded.rotation, q.rotation)
    states = rng.normal(size=(50, 3))
    assert np.array_equal(loaded.values(states), q.values(states))


def test_version_1_files_still_load(tmp_path, policy):
    """A policy written before ensembles (scalar width, no rotation) gives the same values."""
    path = save_policy(policy, tmp_path / "p.npz")
    with zipfile.ZipFile(path) as z:
        arrays = {n[:-4]: np.load(z.open(n)) for n in z.namelist() if n != "metadata.npy"}
    metadata = json.loads(str(np.load(path)["metadata"]))
    old = {k: arrays[k] for k in ("mean", "scale", "centers", "weights")}
    old["width"] = arrays["width"][0]
    del metadata["members"]
    write_archive(tmp_path / "v1.npz", old, {**metadata, "format_version": 1})
    loaded = load_policy(tmp_path / "v1.npz")
    states = np.random.default_rng(1).normal(size=(50, 3))
    assert loaded.q.rotation is None and loaded.q.members == 1
    assert np.array_equal(loaded.q.values(states), policy.q.values(states))


def test_pairing_with_another_model_or_environment_is_refused(policy):
    policy.check_model("f" * 64)
    with pytest.raises(ModelFormatError, match="trained for model ffffffffffff"):
        policy.check_model("0" * 64)
    with pytest.raises(ModelFormatError, match="environment 'partial', not 'full'"):
        policy.check_environment("full")
    with pytest.raises(ModelFormatError, match="3-dimensional states"):
        policy.action(np.zeros(5))


def test_existing_file_is_not_overwritten(tmp_path, policy):
    path = save_policy(policy, tmp_path / "p.npz")
    with pytest.raises(ModelFormatError, match="already exists"):
        save_policy(policy, path)
    save_policy(policy, path, force=True)


def test_truncated_foreign_and_other_version_files_are_refused(tmp_path, policy):
    path = save_policy(policy, tmp_path / "p.npz")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ModelFormatError, match="truncated or foreign"):
        load_policy(truncated)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, weights=np.zeros(3))
    with pytest.raises(ModelFormatError, match="no 'metadata' entry"):
        load_policy(foreign)
    future = tmp_path / "future.npz"
    with zipfile.ZipFile(path) as z:
        arrays = {n[:-4]: np.load(z.open(n)) for n in z.namelist() if n != "metadata.npy"}
    write_archive(future, arrays, {"format": "tpsr-ros policy", "format_version": 99})
    with pytest.raises(ModelFormatError, match=r"format version 99; .* reads version 1 or 2"):
        load_policy(future)
    model = tmp_path / "model.npz"
    write_archive(model, arrays, {"format": "tpsr-ros model", "format_version": 1})
    with pytest.raises(ModelFormatError, match="is a 'tpsr-ros model' file"):
        load_policy(model)


def test_inconsistent_shapes_are_refused(tmp_path, policy):
    path = save_policy(policy, tmp_path / "p.npz")
    with zipfile.ZipFile(path) as z:
        arrays = {n[:-4]: np.load(z.open(n)) for n in z.namelist() if n != "metadata.npy"}
    import json

    metadata = json.loads(str(np.load(path)["metadata"]))
    arrays["weights"] = arrays["weights"][:-1]  # one centre's weights missing
    broken = tmp_path / "broken.npz"
    write_archive(broken, arrays, metadata)
    # (the temporary path holds this test's name, so match more than "inconsistent")
    rule = r"'weights' .* has shape \(9, 4\); its metadata implies \(10, 4\)"
    with pytest.raises(ModelFormatError, match=rule):
        load_policy(broken)


def test_hostile_values_and_metadata_are_refused(tmp_path, policy):
    path = save_policy(policy, tmp_path / "p.npz")
    with zipfile.ZipFile(path) as z:
        arrays = {n[:-4]: np.load(z.open(n)) for n in z.namelist() if n != "metadata.npy"}
    metadata = json.loads(str(np.load(path)["metadata"]))
    cases = [
        ({**arrays, "width": np.array([1e308])}, metadata, "beyond 1e\\+100"),  # width**2 overflows
        ({**arrays, "width": np.array([1e-300])}, metadata, "has inconsistent array shapes"),
        ({**arrays, "group_sizes": np.array([3])}, metadata, "summing to the centres"),
        ({**arrays, "group_sizes": np.array([10.0])}, metadata, "positive int64"),
        (arrays, {**metadata, "members": 2}, r"'width' .* metadata implies \(2,\)"),
        (arrays, {**metadata, "state_dim": "3"}, "valid 'state_dim'"),
        (arrays, {**metadata, "n_centers": 10.0}, "valid 'n_centers'"),
        (arrays, {**metadata, "environment": ["full"]}, "valid 'environment'"),
    ]
    for index, (content, meta, message) in enumerate(cases):
        target = tmp_path / f"bad{index}.npz"
        write_archive(target, content, meta)
        with pytest.raises(ModelFormatError, match=message):
            load_policy(target)
