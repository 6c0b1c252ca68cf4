"""Wall time of ``learner tune`` on a 24000-step `full` bag (within its default
budget of 5 minutes on a 2-core machine), with the candidates it tried and the best."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import yaml

from learner.cli import main as learner
from learner.tune import DEFAULT_BUDGET
from sim_node import SimConfig
from sim_node.generate import generate_bag


def main() -> None:
    with tempfile.TemporaryDirectory() as scratch:
        bag, config = Path(scratch) / "bag", Path(scratch) / "tuned.yaml"
        generate_bag(bag, SimConfig(environment="full"), 24_000, seed=0)
        start = time.perf_counter()
        learner(["tune", str(bag), "-o", str(config)])
        elapsed = time.perf_counter() - start
        record = yaml.safe_load(config.read_text())["tune"]
    print(
        f"learner tune, 24000-step bag: {elapsed:.1f} s of the {DEFAULT_BUDGET:.0f} s budget, "
        f"{len(record['tried'])} candidates; best criterion {record['criterion']:.4f}; "
        f"{record['stopped']}"
    )


if __name__ == "__main__":
    main()
