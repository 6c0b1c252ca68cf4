"""Large bags fast, for benchmarks only: a real simulated run tiled and perturbed.

Simulating 10^6 steps takes far longer than the fit being measured, so
:func:`write_tiled_bag` writes bags of any length from one real run of the simulator
(:func:`sim_node.random_rollout`): step ``k`` of the bag is step ``k mod N`` of the run, with
every pixel perturbed by independent seeded noise in ``{-2, ..., 2}`` (so no two tiles are
byte-identical and zstd cannot collapse them), stamped ``k`` seconds as DESIGN.md requires.
The jump from the last step of one tile to the first of the next is not a real transition,
which does not matter for timing and memory figures; these bags are **not** for judging model
quality. The bag's ``custom_data`` says it is synthetic.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from sim_node import SimConfig, random_rollout
from sim_node.generate import _write_chunk
from sim_node.rollout import Rollout
from sim_node.topics import SimTopics
from tpsr_ros.io.bag import BagWriter, check_bag_path_free

CHUNK = 2048


def base_run(steps: int = 24_000, seed: int = 0) -> Rollout:
    """The real simulated run that the synthetic bags tile."""
    return random_rollout(SimConfig(environment="full"), steps, seed)


def write_tiled_bag(
    path: Path, base: Rollout, steps: int, *, first_step: int = 1, seed: int = 0
) -> None:
    """Write ``steps`` steps (``first_step ..``) tiled from ``base`` to a new bag at ``path``."""
    check_bag_path_free(path)
    topics = SimTopics()
    rng = np.random.default_rng(seed)
    with BagWriter(path) as writer:
        writer.set_custom_data("tpsr_ros.environment", "full")
        writer.set_custom_data(
            "tpsr_ros.generator",
            json.dumps({"synthetic": "tiled and perturbed real run", "steps": steps,
                        "base_steps": len(base), "seed": seed}),
        )  # fmt: skip
        for topic, msgtype in topics.types().items():
            writer.add_topic(topic, msgtype)
        for start in range(0, steps, CHUNK):
            k = first_step + np.arange(start, min(start + CHUNK, steps))
            idx = k % len(base)
            noise = rng.integers(-2, 3, size=(len(k), *base.images.shape[1:]), dtype=np.int16)
            images = np.clip(base.images[idx].astype(np.int16) + noise, 0, 255).astype(np.uint8)
            part = dataclasses.replace(
                base,
                first_step=int(k[0]),
                stamps_ns=k.astype(np.int64) * 1_000_000_000,
                actions=base.actions[idx],
                commands=base.commands[idx],
                executed=base.executed[idx],
                positions=base.positions[idx],
                wall_contact=base.wall_contact[idx],
                goal_zone=base.goal_zone[idx],
                rewards=base.rewards[idx],
                images=images,
            )
            _write_chunk(writer, topics, part)


def write_tiled_bags(
    directory: Path, base: Rollout, steps: int, per_bag: int, *, seed: int = 0
) -> list[Path]:
    """``steps`` steps as consecutive bags of at most ``per_bag`` steps each."""
    paths = []
    for i, start in enumerate(range(0, steps, per_bag)):
        path = directory / f"tiled_{i:03d}"
        write_tiled_bag(
            path, base, min(per_bag, steps - start), first_step=start + 1, seed=seed + i
        )
        paths.append(path)
    return paths
