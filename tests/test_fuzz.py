"""Seeded mutation fuzzing of every file we accept: model and policy archives, bag
``metadata.yaml`` and MCAP bytes, params files.

Each case mutates a valid file (flipped bits, overwritten or duplicated spans, truncation,
huge integers written over lengths) and loads it as the CLI or node would. The only
acceptable outcomes are success or the layer's one-line error (``ModelFormatError``,
``BagError``, ``UsageError``); any other exception is a bug. CI runs ``FUZZ_CASES``
(default 40) cases per family with ``FUZZ_SEED`` 0; ``make fuzz`` runs 2000 per family
with a new seed each time and prints it, so a failure reruns exactly.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from test_tpsr import SMALL, structured_episodes

from tpsr_ros.core.errors import BagError, ModelFormatError
from tpsr_ros.core.fqi import FQIConfig, fit_q
from tpsr_ros.core.tpsr import fit_tpsr
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.model_io import load_model, save_model
from tpsr_ros.io.policy import Policy, load_policy, save_policy
from tpsr_ros.runtime.params import param, resolve_parameters
from tpsr_ros.runtime.ros_args import UsageError, parse_ros_args

CASES = int(os.environ.get("FUZZ_CASES", "40"))
SEED = int(os.environ.get("FUZZ_SEED", "0"))  # make fuzz varies it; CI keeps 0
BAGS = Path(__file__).resolve().parent.parent / "bags"
PARAMS = b"""/**:
  ros__parameters:
    use_sim_time: false
sim_node:
  ros__parameters:
    environment: partial
    seed: 3
    rate: 20.0
    gains: [1.0, 2.5]
    name: "robot"
"""


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One random structural or bit-level change of ``data``."""
    out = bytearray(data)
    kind = int(rng.integers(6))
    at = int(rng.integers(len(out))) if out else 0
    if kind == 0:  # flip bits
        for _ in range(int(rng.integers(1, 8))):
            i = int(rng.integers(len(out)))
            out[i] ^= 1 << int(rng.integers(8))
    elif kind == 1:  # a huge little-endian integer over a length or offset field
        out[at : at + 8] = int(rng.choice([2**31, 2**40, 2**63 - 1, 0])).to_bytes(8, "little")
    elif kind == 2:  # truncate
        del out[at:]
    elif kind == 3:  # duplicate a span
        span = out[at : at + int(rng.integers(1, 4096))]
        out[at:at] = span * int(rng.integers(1, 4))
    elif kind == 4:  # random bytes over a span
        n = int(rng.integers(1, 64))
        out[at : at + n] = rng.integers(0, 256, size=n, dtype=np.uint8).tobytes()
    else:  # delete a span
        del out[at : at + int(rng.integers(1, 256))]
    return bytes(out)


def _fuzz(
    tmp_path: Path, original: bytes, seed: int, load: Callable[[Path], object],
    allowed: type[Exception], name: str,
) -> dict[str, int]:
    rng = np.random.default_rng([SEED, seed])
    outcomes = {"loaded": 0, "refused": 0}
    for case in range(CASES):
        target = tmp_path / f"{case}-{name}"
        target.write_bytes(mutate(original, rng))
        try:
            load(target)
            outcomes["loaded"] += 1
        except allowed as exc:
            assert "\n" not in str(exc), exc
            outcomes["refused"] += 1
        target.unlink()
    return outcomes


@pytest.fixture(scope="module")
def model_bytes(tmp_path_factory) -> bytes:
    h, o, a, t = structured_episodes(200, seed=11)
    path = tmp_path_factory.mktemp("fuzz") / "model.npz"
    save_model(fit_tpsr(h, o, a, t, n_actions=3, config=SMALL), path)
    return path.read_bytes()


def test_fuzz_model_files(tmp_path, model_bytes):
    outcomes = _fuzz(tmp_path, model_bytes, 1, load_model, ModelFormatError, "model.npz")
    assert outcomes["refused"] > 0


def test_fuzz_policy_files(tmp_path):
    rng = np.random.default_rng(0)
    s = rng.normal(size=(400, 3))
    q = fit_q(s, rng.integers(0, 4, 400), rng.normal(size=400), s, 4, FQIConfig(centers=8))
    path = save_policy(Policy(q, "tpsr", "f" * 64, "full"), tmp_path / "p.npz")
    outcomes = _fuzz(tmp_path, path.read_bytes(), 2, load_policy, ModelFormatError, "p.npz")
    assert outcomes["refused"] > 0


def _read_bag(directory: Path) -> None:
    with BagReader(directory) as reader:
        for _ in reader.messages():
            pass


@pytest.mark.slow
def test_fuzz_bag_metadata_and_mcap(tmp_path):
    source = BAGS / "full"
    for name, seed in (("metadata.yaml", 3), ("full.mcap", 4)):
        original = (source / name).read_bytes()
        rng = np.random.default_rng([SEED, seed])
        refused = 0
        for case in range(CASES):
            bag = tmp_path / f"bag{case}"
            shutil.copytree(source, bag)
            (bag / name).write_bytes(mutate(original, rng))
            try:
                _read_bag(bag)
            except BagError as exc:
                assert "\n" not in str(exc), exc
                refused += 1
            shutil.rmtree(bag)
        assert refused > 0, name


def test_fuzz_params_files(tmp_path):
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class Sim:
        environment: str = param("full", "environment")
        seed: int = param(0, "seed")
        rate: float = param(10.0, "rate")
        gains: tuple[float, ...] = param((1.0,), "gains")
        name: str = param("x", "name")

    def load(path: Path) -> object:
        return resolve_parameters(Sim, parse_ros_args(["--params-file", str(path)]), "/sim_node")

    outcomes = _fuzz(tmp_path, PARAMS, 5, load, UsageError, "params.yaml")
    assert outcomes["refused"] > 0
