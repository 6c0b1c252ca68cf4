"""The end-to-end demo behind ``make demo``.

Writes everything under ``demo_output/`` (its own scratch directory, recreated on every
run) and prints what it made. So far: one random-exploration bag per environment.
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

from sim_node import SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.bag import BagReader
from tpsr_ros.cli import ArgumentParser, positive_int, run_cli

__all__ = ["main"]

PROG = "python -m learner.demo"


def main(argv: list[str] | None = None) -> int:
    """Run the demo."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--output", type=Path, default=Path("demo_output"))
    parser.add_argument("--steps", type=positive_int, default=5000, help="steps per bag")
    args = parser.parse_args(argv)
    if args.output.exists():
        shutil.rmtree(args.output)
    (args.output / "bags").mkdir(parents=True)
    for environment in ("full", "partial", "distractors"):
        bag = args.output / "bags" / environment
        start = time.perf_counter()
        generate_bag(bag, SimConfig(environment=environment), args.steps, seed=1, progress=True)
        elapsed = time.perf_counter() - start
        with BagReader(bag) as reader:
            counts = ", ".join(f"{t} {n}" for t, n in sorted(reader.message_counts.items()))
        print(f"{bag}: {args.steps} steps in {elapsed:.1f} s; {counts}", file=sys.stderr)
    print(f"demo finished; outputs in {args.output}/")
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
