"""How far apart the memory experiment's two runs are in the *true* predictive state.

``python -m benchmarks.memory_oracle --test-length 8 [--steps 150000] [--rollouts 200]
[--experiment paths|stand-still] [--set NAME=VALUE]``

A TPSR's state is ``U^T E[phi_T | history]``. In ``partial`` its best possible value is
``U^T E[phi_T | position]``: the position is the whole hidden state. This script fits the
parts of a TPSR that define the state space (test whitening, centres, ``U``) on a random
run, then estimates ``E[U^T phi_T | position]`` by Monte Carlo (``--rollouts`` random
continuations of ``n`` steps from the exact position, the test window of ``P_TH``) at every
position of one of ``learner memory``'s experiments from its first identical step until both
runs stand still, and prints their distance relative to the spread of such states over the
room (the same positions' states smoothed from the training data, 400 random training
positions). The noise of the estimate is printed beside it: two independent sets of
rollouts from one position; it inflates the distance (squared, the two add). It is a rough
bound of what ``learner memory`` can measure for a TPSR with these tests whose filter
tracks the true predictive state: a distance under the threshold (0.1) here means the tests
cannot tell the two positions apart, however good the fit. (The spread here is over exact
positions' states, ``learner memory``'s over a filter's states: comparable, not equal.)
Not a timed benchmark (not run by ``make bench``).
"""

from __future__ import annotations

import argparse

import numpy as np

from learner import memory
from learner.overrides import apply_overrides
from learner.simulated import random_trajectory
from sim_node import RobotEnv, SimConfig
from tpsr_ros.cli import positive_int
from tpsr_ros.core import tpsr
from tpsr_ros.core.action_features import join_actions, standardised_codes
from tpsr_ros.core.actions import NUM_ACTIONS
from tpsr_ros.core.episodes import images_to_observations, make_episodes
from tpsr_ros.core.tpsr_stages import ht_features, kernel_centres, truncated_svd
from tpsr_ros.core.whitened import Whitenings

ENVIRONMENT = "partial"


def fitted_state_space(cfg: tpsr.TPSRConfig, steps: int, seed: int):
    """The test whitening, test centres and ``U`` of a fit, and per-sample projected tests."""
    episodes = make_episodes(random_trajectory(ENVIRONMENT, steps, seed), cfg.history_length,
                             cfg.test_length)
    codes = standardised_codes(None, NUM_ACTIONS) if cfg.uses_actions else None
    whitenings, rows = Whitenings.fit(episodes, cfg, codes)
    c_h, c_t, _ = kernel_centres(rows.history, rows.test, rows.observation, cfg)
    train = slice(max(cfg.ht_centers, cfg.obs_centers) if cfg.center_selection == "first" else 0,
                  None)
    phi_h = ht_features(rows.history[train], c_h, cfg)
    tests = rows.test if rows.test0 is None else rows.test0
    phi_t0 = ht_features(tests[train], c_t, cfg)
    p_th = phi_t0.T @ phi_h / len(phi_h)
    u = truncated_svd(p_th, cfg)[0]
    return whitenings.test, c_t, u, phi_t0 @ u, episodes.positions[train]


def monte_carlo_state(position, cfg, whitening, centres, u, rollouts: int, seed: int):
    """``E[U^T phi_T | position]`` over ``rollouts`` random continuations (the P_TH window)."""
    env = RobotEnv(SimConfig(environment=ENVIRONMENT), seed=seed)
    rng = np.random.default_rng(seed)
    n, from_current = cfg.test_length, cfg.p_th_tests == "from-current"
    tests, actions = [], rng.integers(0, NUM_ACTIONS, size=(rollouts, n))
    for row in actions:
        image, _ = env.reset(options={"position": tuple(position)})
        images = [image] if from_current else []
        images += [env.step(int(a))[0] for a in row[: n - 1 if from_current else n]]
        tests.append(images_to_observations(np.stack(images)).reshape(-1))
    if from_current:  # the current step's action is unknown here: a random one
        actions = np.concatenate([rng.integers(0, NUM_ACTIONS, (rollouts, 1)), actions[:, :-1]],
                                 axis=1)
    white = join_actions(whitening.transform(np.array(tests)), actions,
                         standardised_codes(None, NUM_ACTIONS), cfg.test_action_weight, "test")
    return (ht_features(white, centres, cfg) @ u).mean(axis=0)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.memory_oracle")
    parser.add_argument("--test-length", type=positive_int, default=1)
    parser.add_argument("--steps", type=positive_int, default=60000)
    parser.add_argument("--rollouts", type=positive_int, default=200)
    parser.add_argument("--experiment", choices=[e.name for e in memory.EXPERIMENTS],
                        default=memory.EXPERIMENTS[0].name)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args(argv)
    base = tpsr.TPSRConfig(rank=10, test_length=args.test_length)
    cfg = apply_overrides({"tpsr": base}, args.set)["tpsr"]
    whitening, centres, u, projected, positions = fitted_state_space(cfg, args.steps, 0)
    rng = np.random.default_rng(0)
    grid = positions[rng.choice(len(positions), 400, replace=False)]
    weights = np.exp(-np.sum((positions[None] - grid[:, None]) ** 2, axis=2) / (2 * 1.5**2))
    smoothed = (weights @ projected) / weights.sum(axis=1, keepdims=True)
    spread = np.sqrt(np.mean(np.sum((smoothed - smoothed.mean(axis=0)) ** 2, axis=1)))
    experiment = next(e for e in memory.EXPERIMENTS if e.name == args.experiment)
    runs = memory.simulate(experiment, ENVIRONMENT)
    start = memory.identical_from(*runs)
    print(f"tests of {cfg.test_length}, {cfg.p_th_tests}, test action weight "
          f"{cfg.test_action_weight}; relative distance (noise) by position:")
    for step in range(start, len(runs[0].positions)):
        a, b = runs[0].positions[step], runs[1].positions[step]
        if step > start and np.allclose(a, runs[0].positions[step - 1]):
            break
        state = [monte_carlo_state(p, cfg, whitening, centres, u, args.rollouts, s)
                 for p, s in ((a, 1), (b, 2), (a, 3))]
        print(f"  ({a[0]:.1f}, {a[1]:.1f}) vs ({b[0]:.1f}, {b[1]:.1f}): "
              f"{np.linalg.norm(state[0] - state[1]) / spread:.3f} "
              f"({np.linalg.norm(state[0] - state[2]) / spread:.3f})", flush=True)


if __name__ == "__main__":
    main()
