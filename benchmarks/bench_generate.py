"""Bag generation throughput (simulate, render, serialise, write MCAP) on one core.

Each run happens in a child process pinned to one CPU with single-threaded BLAS, so the
figure is per core. Target: at least 5000 steps/s.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

import numpy as np

STEPS = 10000
REPEATS = 3
TARGET = 5000.0

_CHILD = """
import json, os, sys, time
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
from sim_node import SimConfig
from sim_node.generate import generate_bag
environment, steps, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
start = time.perf_counter()
generate_bag(out, SimConfig(environment=environment), steps, seed=0)
elapsed = time.perf_counter() - start
size = sum(os.path.getsize(os.path.join(out, f)) for f in os.listdir(out))
print(json.dumps({"seconds": elapsed, "bytes": size}))
"""


def _one_run(environment: str, directory: str, index: int) -> dict[str, float]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = os.path.join(directory, f"{environment}-{index}")
    result = subprocess.run(
        [sys.executable, "-c", _CHILD, environment, str(STEPS), out],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    print(f"generation with bag writing, {STEPS} steps, median of {REPEATS} runs, one core")
    with tempfile.TemporaryDirectory() as directory:
        for environment in ("full", "partial", "distractors"):
            runs = [_one_run(environment, directory, i) for i in range(REPEATS)]
            rate = float(np.median([STEPS / r["seconds"] for r in runs]))
            size = float(np.median([r["bytes"] for r in runs])) / STEPS
            verdict = "ok" if rate >= TARGET else "BELOW TARGET"
            print(
                f"  {environment:12s} {rate:8.0f} steps/s  ({rate / TARGET:.1f}x the "
                f"{TARGET:.0f} target, {verdict}); {size:.0f} bytes/step on disk"
            )


if __name__ == "__main__":
    main()
