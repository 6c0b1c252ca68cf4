"""A refined TPSR fit of 24000 steps on one core: the spectral fit and the refinement's share.

Data: a uniformly random 24000-step run of ``partial-strip`` (8000 of the guide's
episodes), made in memory. Fit: the default preset, ``predictive`` (``best`` with
from-current ``P_TH`` tests, histories of two images, a window at every step and 30
iterations of refinement through the filter),
sized to the data as ``learner fit`` sizes it, with BLAS on one thread. Target: the whole
fit within 60 s.
Printed per repeat: the spectral stages, the refinement (iterations, best iteration,
held-out unexplained variance before and after) and the total; then the medians.
"""

from __future__ import annotations

import statistics
import time

from threadpoolctl import threadpool_limits

from learner.simulated import random_trajectory
from tpsr_ros.core.learn import fit_tpsr_trajectory
from tpsr_ros.core.presets import get_preset
from tpsr_ros.core.sizing import Sizing

STEPS = 24_000
ENVIRONMENT = "partial-strip"
SEEDS = (0, 1, 2)
TARGET_SECONDS = 60.0


def main() -> None:
    config = get_preset("predictive").tpsr_config()
    totals, refinements = [], []
    with threadpool_limits(1):
        for seed in SEEDS:
            train = random_trajectory(ENVIRONMENT, STEPS, seed)
            start = time.perf_counter()
            model = fit_tpsr_trajectory(train, config, sizing=Sizing())
            total = time.perf_counter() - start
            refined = model.fit_info["refinement"]
            totals.append(total)
            refinements.append(refined["seconds"])
            print(
                f"seed {seed}: fit {total:.1f} s = spectral {total - refined['seconds']:.1f} s "
                f"+ refinement {refined['seconds']:.1f} s ({refined['iterations']} iterations, "
                f"best {refined['best_iteration']}; held-out unexplained "
                f"{refined['heldout_unexplained_spectral']:.4f} -> "
                f"{refined['heldout_unexplained']:.4f})",
                flush=True,
            )
    total, share = statistics.median(totals), statistics.median(refinements)
    print(
        f"refined fit of {STEPS} {ENVIRONMENT} steps on one core: median {total:.1f} s "
        f"(refinement {share:.1f} s, {100 * share / total:.0f} %) [target <= {TARGET_SECONDS:g} s]"
    )


if __name__ == "__main__":
    main()
