"""The end-to-end demo behind ``make demo``: simulate, record, learn, plan, filter, control.

Everything goes to ``demo_output/<environment>/`` (recreated on every run of that
environment; the other environments' outputs are left alone):

1. a random training run (24000 steps) and a separate random RL run (15000 steps; 20000
   in the other environments, as in the guide's ``partial``) of the simulator, written as bags
   (``python -m sim_node.generate``);
2. a TPSR (``learner fit``) and a fitted-Q policy on the states tracked over the RL run
   (``learner policy``), both with the default preset (``predictive``; ``--preset guide`` for the
   guide's settings);
3. the standard evaluation headless (``learner evaluate``), beside the floors (the best
   constant action, uniformly random actions) and the ceiling (fitted Q on the true
   position), then over the nodes: sim_node and the filter node as separate processes in
   lockstep over ROS 2 (rclpy when importable, else the DDS backend), recorded into a bag
   (``learner closed-loop --record``); the two scores are equal by construction;
4. plots: the states over the RL run coloured by reward and true position (``learner
   plot``), and the closed-loop trajectories from ``/ground_truth/pose`` coloured by trial.
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any


from learner.cli import main as learner_main
from learner.closed_loop import run_closed_loop
from learner.evaluate import START_POSITIONS, STEPS, evaluate
from learner.experiment import RL_STEPS
from learner.floors import DEMO_POLICY_SEED, ConstantFloor, constant_floor, random_floor
from learner.options import add_preset_option
from learner.representations import load_tracker
from sim_node import Environment, SimConfig
from sim_node.generate import generate_bag
from sim_node.options import add_vertical_half_extent_option
from tpsr_ros.cli import ArgumentParser, positive_int, run_cli
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.policy import TRUE_POSITION, load_policy
from tpsr_ros.runtime.backend import choose_backend
from tpsr_ros.progress import progress_bar

__all__ = ["Bounds", "bounds_line", "main", "plot_trajectories"]

DEMO_OUTPUT = Path("demo_output")
"""Where each environment's run goes by default (``demo_output/<environment>``)."""
PROG = "python -m learner.demo"
STAGES = 7


def _stage(number: int, text: str) -> None:
    print(f"[{number}/{STAGES}] {text}", file=sys.stderr, flush=True)


def plot_trajectories(bag: Path, output: Path, config: SimConfig | None = None) -> int:
    """Plot the ``/ground_truth/pose`` path of every episode in ``bag``, coloured by trial.

    Episodes are split at the ``/sim/episode_start`` stamps; the goal zone (a quarter disk
    at the north-east corner) and the walls are drawn. Returns the number of episodes.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    config = config or SimConfig()
    def stamped_positions(topic: str) -> list[tuple[int, tuple[float, float]]]:
        decoded = (msg.decode() for msg in reader.messages([topic]))
        return sorted((m.stamp_of(pose), m.pose_to_xy(pose)) for pose in decoded)

    with BagReader(bag) as reader:
        starts = stamped_positions("/sim/episode_start")
        poses = stamped_positions("/ground_truth/pose")
    episodes = [
        [start] + [xy for stamp, xy in poses if t < stamp < (nxt[0] if nxt else float("inf"))]
        for (t, start), nxt in zip(starts, [*starts[1:], None], strict=True)
    ]
    episodes = [e for e in episodes if len(e) > 1]
    size = config.room_size
    fig, ax = plt.subplots(figsize=(8.5, 7))
    room = Rectangle((0, 0), size, size, fill=False, linewidth=2, color="black")
    ax.add_patch(room)
    goal = Circle((size, size), config.goal_radius, color="gold", alpha=0.35, label="goal zone")
    ax.add_patch(goal)
    goal.set_clip_path(room)
    colours = plt.get_cmap("tab10")
    for index, path in enumerate(episodes):
        xs, ys = zip(*path, strict=True)
        colour = colours(index % 10)
        ax.plot(xs, ys, "-", color=colour, linewidth=1.2, alpha=0.9, label=f"trial {index + 1}")
        ax.plot(xs[0], ys[0], "o", color=colour, markersize=7)
        ax.plot(xs[-1], ys[-1], "x", color=colour, markersize=7)
    ax.set_xlim(-1, size + 1)
    ax.set_ylim(-1, size + 1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("closed loop over the nodes: true paths (o start, x after the last step)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(output, dpi=90)
    plt.close(fig)
    return len(episodes)


def main(argv: list[str] | None = None) -> int:
    """Run the demo."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument(
        "--output",
        type=Path,
        default=None,
        help="output directory, recreated (default: demo_output/<environment>, so runs of "
        "other environments keep theirs)",
    )
    parser.add_argument(
        "--environment",
        choices=[e.value for e in Environment],
        default="full",
        help="camera (default: %(default)s)",
    )
    add_vertical_half_extent_option(parser)
    parser.add_argument(
        "--domain-id",
        type=int,
        default=None,
        metavar="N",
        help="ROS_DOMAIN_ID of the closed loop (default: a free one in 1..101 at random)",
    )
    parser.add_argument(
        "--train-steps",
        type=positive_int,
        default=24_000,
        help="steps of the random training run (default: %(default)s)",
    )
    parser.add_argument(
        "--rl-steps",
        type=positive_int,
        default=None,
        help="steps of the random RL run (default: the guide's, 15000 in full and 20000 "
        "otherwise)",
    )
    add_preset_option(parser, "fit and fitted-Q (learner fit and learner policy)")
    parser.add_argument(
        "--view",
        nargs="?",
        type=int,
        const=8765,
        default=None,
        metavar="PORT",
        help="serve the closed loop to Foxglove while it runs (python -m tpsr_ros.view; the "
        "view extra), on PORT (default 8765)",
    )
    parser.add_argument(
        "--fit-option",
        action="append",
        default=[],
        metavar="OPTION",
        help="extra `learner fit` option, repeatable (e.g. --fit-option=--rank=3)",
    )
    args = parser.parse_args(argv)
    began = time.perf_counter()
    out: Path = args.output if args.output is not None else DEMO_OUTPUT / args.environment
    if out.exists():
        shutil.rmtree(out)
    (out / "bags").mkdir(parents=True)
    env = args.environment
    sim = SimConfig(environment=env, vertical_half_extent=args.vertical_half_extent)
    rl_steps = args.rl_steps or RL_STEPS[env]
    train, rl, closed = out / "bags" / "train", out / "bags" / "rl", out / "bags" / "closed_loop"
    model, policy = out / "model.npz", out / "policy.npz"

    _stage(1, f"simulating the training run: {args.train_steps} random steps ({env}) -> {train}")
    generate_bag(train, sim, args.train_steps, seed=0, progress=True)
    _stage(2, f"simulating the RL run: {rl_steps} random steps ({env}) -> {rl}")
    generate_bag(rl, sim, rl_steps, seed=1, progress=True)

    preset = ["--preset", args.preset]
    _stage(3, f"learner fit {train} -o {model} --preset {args.preset}")
    learner_main(["fit", str(train), "-o", str(model), *preset, *args.fit_option])
    _stage(4, f"learner policy {model} {rl} -o {policy} --preset {args.preset}  (fitted Q)")
    learner_main(["policy", str(model), str(rl), "-o", str(policy), *preset])

    _stage(5, f"learner evaluate {policy} --environment {env}  (headless; floors, ceiling)")
    headless = evaluate(load_policy(policy), load_tracker(model), sim)
    ceiling_policy = out / "policy_true_position.npz"
    learner_main(["policy", TRUE_POSITION, str(rl), "-o", str(ceiling_policy), *preset])
    bounds = Bounds(
        constant_floor(env),
        random_floor(env, policy_seed=DEMO_POLICY_SEED).score,
        evaluate(load_policy(ceiling_policy), load_tracker(TRUE_POSITION), sim).score,
    )

    _stage(
        6,
        f"closed loop over the nodes: sim_node + tpsr_filter as processes over "
        f"{choose_backend()[0]}, recorded to {closed}",
    )
    with progress_bar(total=len(START_POSITIONS) * STEPS, unit="step", desc="closed loop") as bar:
        result = run_closed_loop(
            policy,
            env,
            vertical_half_extent=args.vertical_half_extent,
            domain_id=args.domain_id,
            model_path=model,
            record=closed,
            log_dir=out / "logs",
            on_step=bar.update,
            say=lambda text: bar.write(f"      {text}", file=sys.stderr),
            view_port=args.view,
        )

    _stage(7, "plots")
    states_png, paths_png = out / "states.png", out / "trajectories.png"
    learner_main(["plot", str(model), str(rl), "-o", str(states_png)])
    plot_trajectories(closed, paths_png, sim)
    view_png = out / "view.png"
    learner_main(["view-figure", str(closed), "-o", str(view_png), "--title",
                  f"what the filter node showed in the closed loop ({env})"])  # fmt: skip

    _summary(out, headless, result, bounds, time.perf_counter() - began)
    return 0


@dataclass(frozen=True)
class Bounds:
    """What the score stands between: the state-blind floors and the true-position ceiling."""

    constant: ConstantFloor
    random: float
    true_position: float


def bounds_line(bounds: Bounds) -> str:
    """The floors and the ceiling under the standard evaluation, naming the floors' own
    protocol: one run each, random actions from :data:`DEMO_POLICY_SEED`, where the results
    page pools every run of its experiments (so the two random floors differ)."""
    first, second = bounds.constant.velocity
    return (
        f"same protocol, floors (one run each; random actions: policy seed {DEMO_POLICY_SEED}): "
        f"best constant action ({first:+.3g}, {second:+.3g}) "
        f"{bounds.constant.evaluation.score:.1f}, random actions {bounds.random:.1f}; "
        f"ceiling: true position {bounds.true_position:.1f}"
    )


def _summary(out: Path, headless: Any, result: Any, bounds: Bounds, seconds: float) -> None:
    print()
    print("trial  start           closed loop (reward, goal step)  headless")
    for index, (ours, theirs) in enumerate(
        zip(result.evaluation.trials, headless.trials, strict=True)
    ):
        goal = f"step {ours.goal_step}" if ours.goal_step else "never"
        print(
            f"{index + 1:5d}  ({ours.start[0]:4.1f}, {ours.start[1]:4.1f})  "
            f"{ours.reward:7.1f}, goal zone {goal:8s}         {theirs.reward:7.1f}"
        )
    closed, head = result.evaluation.score, headless.score
    same = "identical" if closed == head else "DIFFERENT"
    print(
        f"score over the nodes (closed loop): {closed:.1f}; headless (learner evaluate): "
        f"{head:.1f} ({same})"
    )
    print(bounds_line(bounds))
    reached = sum(t.goal_step is not None for t in result.evaluation.trials)
    print(f"the robot reached the goal zone in {reached} of {len(result.evaluation.trials)} trials")
    print()
    print(f"outputs in {out}/ (demo took {seconds:.0f} s):")
    for path, what in [
        ("bags/train", "random training run (rosbag2, MCAP)"),
        ("bags/rl", "random RL run"),
        ("model.npz", "TPSR (learner info model.npz)"),
        ("policy.npz", "greedy fitted-Q policy for that model"),
        ("policy_true_position.npz", "the ceiling: fitted Q on the true position"),
        (
            "bags/closed_loop",
            "closed-loop recording: images, actions, /tpsr/state and the view topics, "
            "/cmd_vel, /reward, /ground_truth/pose, /diagnostics",
        ),
        ("logs/", "the nodes' logs"),
        ("states.png", "states over the RL run coloured by reward, true x and y"),
        ("trajectories.png", "closed-loop paths by trial, with the goal zone"),
        ("view.png", "what the view topics showed at one closed-loop step (learner view-figure)"),
    ]:
        print(f"  {out / path}: {what}")


if __name__ == "__main__":
    run_cli(PROG, main)
