"""Offline bag generation: a uniformly random run written straight to a rosbag2 MCAP bag.

    python -m sim_node.generate --environment full --steps 24000 --seed 0 -o bags/full

Writes the topics and stamps of DESIGN.md with no middleware, as fast as the machine
allows. The output path must not exist; on any error or Ctrl-C the partial bag is
removed. The generator's settings are stored in the bag's ``custom_data``.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

from sim_node.batch_cdr import chunk_payloads
from sim_node.config import Environment, SimConfig
from sim_node.options import add_vertical_half_extent_option
from sim_node.rollout import Rollout, iter_random_rollout
from sim_node.topics import SimTopics
from tpsr_ros.cli import ArgumentParser, positive_int, run_cli
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.bag import BagWriter, check_bag_path_free
from tpsr_ros.progress import progress_bar

__all__ = ["generate_bag", "main"]

PROG = "python -m sim_node.generate"


SWITCH_SEED_OFFSET = 1_000_003
"""Added to a run's seed for its random streams after the room changes (``then``)."""


def _write_chunk(writer: BagWriter, topics: SimTopics, part: Rollout, config: SimConfig) -> None:
    """Write every message of the chunk's steps, in step order (CDR built per chunk)."""
    payloads = chunk_payloads(topics, part, config)
    order = list(topics.types())
    for i, stamp in enumerate(part.stamps_ns.tolist()):
        for topic in order:
            writer.write(topic, stamp, payloads[topic][i])


def generate_bag(
    output: Path,
    config: SimConfig,
    steps: int,
    seed: int,
    *,
    topics: SimTopics | None = None,
    progress: bool = False,
    then: tuple[SimConfig, int] | None = None,
) -> int:
    """Simulate ``steps`` random steps and write them to a new bag; returns messages written.

    ``then`` (another room's config and a number of steps): the room changes under the
    robot after ``steps`` steps, and the run goes on there from the robot's last position,
    its stamps continuing (its random streams drawn from ``seed + SWITCH_SEED_OFFSET``).
    """
    topics = topics or SimTopics()
    check_bag_path_free(output)
    if then is not None and then[0].drives != config.drives:
        raise ConfigError("a run changes rooms only between rooms of the same robot and actions")
    with BagWriter(output) as writer:
        settings = {
            "environment": config.environment.value,
            "seed": seed,
            "steps": steps,
            # the camera as rendered: an environment's own extent, when none was given
            "config": {
                **dataclasses.asdict(config),
                "vertical_half_extent": config.vertical_extent,
            },
        }
        writer.set_custom_data("tpsr_ros.generator", json.dumps(settings, default=str))
        writer.set_custom_data("tpsr_ros.environment", config.environment.value)
        for topic, msgtype in topics.types().items():
            writer.add_topic(topic, msgtype)
        with progress_bar(
            total=steps, unit="step", disable=not progress, desc=config.environment.value
        ) as bar:
            for part in iter_random_rollout(config, steps, seed):
                _write_chunk(writer, topics, part, config)
                bar.update(len(part))
        if then is not None:
            after, more = then
            after = dataclasses.replace(after, start_time_ns=int(part.stamps_ns[-1]))
            start = tuple(part.positions[-1].tolist())
            writer.set_custom_data(
                "tpsr_ros.switch", json.dumps({"after_steps": steps, "environment":
                                               after.environment.value, "steps": more})
            )  # fmt: skip
            for part in iter_random_rollout(after, more, seed + SWITCH_SEED_OFFSET, start=start):
                _write_chunk(writer, topics, part, after)
        return writer.message_count


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and generate one bag."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument(
        "--environment",
        required=True,
        choices=[e.value for e in Environment],
        help="full (300 deg camera), partial (60 deg) or distractors",
    )
    add_vertical_half_extent_option(parser)
    parser.add_argument("--steps", required=True, type=positive_int, help="number of steps")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random stream")
    parser.add_argument("-o", "--output", required=True, type=Path, help="new bag directory")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if args.seed < 0:
        parser.error(f"argument --seed: {args.seed} is negative")
    config = SimConfig(environment=args.environment, vertical_half_extent=args.vertical_half_extent)
    start = time.perf_counter()
    count = generate_bag(args.output, config, args.steps, args.seed, progress=not args.quiet)
    elapsed = time.perf_counter() - start
    if not args.quiet:
        print(
            f"wrote {args.output}: {args.steps} steps, {count} messages in {elapsed:.1f} s "
            f"({args.steps / elapsed:.0f} steps/s)",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
