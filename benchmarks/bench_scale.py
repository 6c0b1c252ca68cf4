"""Scale of the streamed fit: steps/s and peak RSS at 10^5 and 10^6 steps, the
speedup of 2 local Dask workers over 1, and fit time and peak memory at 1 000 / 5 000 /
20 000 history/test centres.

Data: synthetic bags tiled from one real 24 000-step simulated run with perturbed pixels
(``benchmarks/synthetic_bags.py``; good for timing and memory, not for model quality), in
bags of 25 000 steps. Every fit is ``learner fit --stream`` (or ``--workers N``) in a child
process; its peak RSS is the child's ``ru_maxrss`` (``os.wait4``). That figure is the
largest of the child and the descendants it reaped, so for ``--workers`` it is the max of
the client and the LocalCluster's worker processes, not the client alone. The machine is
shared: the load average is printed with every figure. ``SCALE_MAX_STEPS`` (default
1000000) caps the largest run.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.synthetic_bags import base_run, write_tiled_bags
from tpsr_ros.io.model_io import load_model

PER_BAG = 25_000
CENTRE_STEPS = 75_000  # 25 000 episodes: 'first' centres leave 24 000 / 20 000 / 5 000 to train
CENTRES = (1_000, 5_000, 20_000)


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load {one:.1f}/{five:.1f}/{fifteen:.1f} on {os.cpu_count()} CPUs"


def _fit(bags: list[Path], out: Path, *options: str) -> tuple[float, float, dict[str, float]]:
    """Run ``learner fit`` in a child; wall seconds, peak RSS (MiB), stage timings."""
    argv = [sys.executable, "-m", "learner", "fit", *map(str, bags), "-o", str(out), "--force"]
    with tempfile.TemporaryFile("w+") as log:
        start = time.perf_counter()
        child = subprocess.Popen([*argv, *options], stdout=log, stderr=log)
        _, status, usage = os.wait4(child.pid, 0)  # the child's own rusage
        child.returncode = os.waitstatus_to_exitcode(status)
        seconds = time.perf_counter() - start
        if child.returncode != 0:
            log.seek(0)
            raise RuntimeError(f"learner fit failed: {log.read().strip().splitlines()[-1:]}")
    timings = load_model(out).fit_info.get("timings", {})
    return seconds, usage.ru_maxrss / 1024, timings


def _stages(timings: dict[str, float]) -> str:
    return "; ".join(f"{name} {sec:.1f} s" for name, sec in timings.items())


def _streamed(root: Path, base, steps: int) -> list[Path]:
    start = time.perf_counter()
    bags = write_tiled_bags(_mkdir(root / f"s{steps}"), base, steps, PER_BAG)
    size = sum(f.stat().st_size for b in bags for f in b.iterdir()) / 2**20
    print(
        f"  wrote {steps:,} synthetic steps in {len(bags)} bags ({size:.0f} MB) in "
        f"{time.perf_counter() - start:.0f} s",
        flush=True,
    )
    seconds, rss, timings = _fit(bags, root / "model.npz", "--stream")
    fit = sum(timings.values())
    print(
        f"  streamed fit of {steps:,} steps: {seconds:.0f} s wall ({steps / seconds:,.0f} "
        f"steps/s; stages {fit:.0f} s), peak RSS {rss:,.0f} MiB "
        f"({'under' if rss < 2048 else 'OVER'} 2 GiB); {_load()}",
        flush=True,
    )
    print(f"    stages: {_stages(timings)}", flush=True)
    return bags


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def _dask(root: Path, bags: list[Path]) -> None:
    results = {}
    for workers in (1, 2):
        seconds, rss, timings = _fit(bags, root / "model.npz", "--workers", str(workers))
        results[workers] = (seconds, sum(timings.values()), timings)
        print(
            f"  Dask, {workers} local worker(s), {len(bags)} bags: {seconds:.1f} s wall (incl. "
            f"cluster start), stages {results[workers][1]:.1f} s; peak RSS (max of client "
            f"and workers) {rss:,.0f} MiB; {_load()}",
            flush=True,
        )
        print(f"    stages: {_stages(timings)}", flush=True)
    print(
        f"  speedup of 2 workers over 1: {results[1][1] / results[2][1]:.2f}x (stages), "
        f"{results[1][0] / results[2][0]:.2f}x (wall)",
        flush=True,
    )


def _centres(root: Path, base) -> None:
    bags = write_tiled_bags(_mkdir(root / "centres"), base, CENTRE_STEPS, PER_BAG, seed=7)
    for count in CENTRES:
        seconds, rss, timings = _fit(
            bags, root / "model.npz", "--stream", "--ht-centers", str(count)
        )
        print(
            f"  {count:>6,} history/test centres ({CENTRE_STEPS // 3 - count:,} training "
            f"episodes): {seconds:.0f} s wall, peak RSS {rss:,.0f} MiB; {_load()}",
            flush=True,
        )
        print(f"    stages: {_stages(timings)}", flush=True)


def main() -> None:
    largest = int(os.environ.get("SCALE_MAX_STEPS", "1000000"))
    print(
        f"streamed TPSR fit at scale; guide settings (l_O 500, rank 5); {_load()}", flush=True
    )
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
        root = Path(tmp)
        base = base_run()
        small = _streamed(root, base, min(100_000, largest))
        _dask(root, small)
        if largest > 100_000:
            big = _streamed(root, base, largest)
            for bag in big:
                shutil.rmtree(bag)
        _centres(root, base)


if __name__ == "__main__":
    main()
