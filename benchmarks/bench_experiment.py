"""Wall time of one environment's whole experiment grid (target: < 15 minutes).

The default grid of ``learner experiment --environment full``: 4 data sizes x 10
repetitions x (constant and random floors, TPSR, PCA, true position) = 200 runs, of
which 120 learn and plan, on every core.
"""

from __future__ import annotations

import os
import time

from learner.experiment import default_config, run_experiment
from learner.tables import margin_text, summarise

TARGET_S = 15 * 60


def main() -> None:
    workers = os.cpu_count() or 1
    config = default_config("full")
    start = time.perf_counter()
    rows = run_experiment(config, workers=workers, progress=False)
    elapsed = time.perf_counter() - start
    cells = len(config.episodes) * config.repetitions
    print(
        f"experiment grid 'full': {len(rows)} runs ({cells} training trajectories) on "
        f"{workers} workers in {elapsed:.0f} s = {elapsed / 60:.1f} min "
        f"({elapsed / TARGET_S:.2f} of the 15 min target); {elapsed / cells:.1f} s per cell"
    )
    best = max(summarise(rows), key=lambda t: (t["method"] == "tpsr", t["episodes"]))
    print(
        f"  sanity: TPSR mean at {best['episodes']} episodes = {best['mean']:.1f} "
        f"(margin {margin_text(best)}, in SEMs)"
    )


if __name__ == "__main__":
    main()
