"""``learner fit BAG... -o MODEL``: learn a TPSR (or the PCA baseline) from bags.

Every parameter of guide table 3.5 is an option generated from the fields of
:class:`~tpsr_ros.core.tpsr.TPSRConfig` (name, default, help and choices spelled once, there);
the PCA baseline's from :class:`~tpsr_ros.core.pca_baseline.PCAConfig` and the topic names from
:class:`~tpsr_ros.io.trajectory.Topics`. The TPSR options change the ``--preset`` (default
``predictive``, the project's best settings; ``guide``, the guide's: :mod:`tpsr_ros.core.presets`),
and the model records the preset and what the options changed in it. Stage lines go to
stderr, the summary to stdout.

``--stream`` runs :func:`~tpsr_ros.core.streamed_fit.fit_tpsr_streamed` over the bags in
chunks (two passes, memory bounded by chunk and centre counts; same model to 1e-9);
``--workers N`` / ``--scheduler ADDRESS`` run its passes on Dask (:mod:`learner.distributed`).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from learner.adequacy import Adequacy, assess, recovery_text
from learner.config_file import describe, read_fit_file
from learner.distributed import (
    DEFAULT_TIMEOUT,
    DaskEngine,
    check_bags_readable_here,
    check_bags_visible,
    dask_client,
)
from learner.info import kernel_line, predicted_images
from learner.inputs import (
    add_stream_options,
    apply_config_inputs,
    environment_label,
    far_commands_line,
    fit_options_from_args,
    read_for_model,
    require_given_topics,
    robot_turns,
    topics_from_args,
)
from learner.options import (
    add_config_options,
    add_preset_option,
    config_from_args,
    preset_from_args,
)
from tpsr_ros.cli import positive_float, positive_int
from tpsr_ros.core.episodes import Trajectory, common_value, make_episodes, track_trajectory
from tpsr_ros.core.errors import ConfigError, TpsrError
from tpsr_ros.core.pca_baseline import PCAConfig, PCAModel, fit_pca
from tpsr_ros.core.presets import Preset, departures
from tpsr_ros.core.refit import fit_trajectory, view_of_track
from tpsr_ros.core.sizing import Sizing, describe_sizing
from tpsr_ros.core.state_model import StateModel
from tpsr_ros.core.streamed_fit import fit_pca_streamed, fit_tpsr_streamed
from tpsr_ros.core.tpsr import TPSRConfig, TPSRModel
from tpsr_ros.core.view_readout import ViewReadout, ViewSums, point_rows
from tpsr_ros.io.bag_chunks import DEFAULT_CHUNK_STEPS, BagChunks, survey_bags
from tpsr_ros.io.bag_streams import pose_frame_id
from tpsr_ros.io.model_io import check_output_path, open_model, save_model
from tpsr_ros.io.stream_defaults import check_fit_memory, grid_step_count
from tpsr_ros.io.stream_spec import StreamSpec
from tpsr_ros.io.streams import (
    DEFAULT_POSE_FRAME,
    BagStreams,
    FitOptions,
    fit_stream_spec,
    read_bag_streams,
    read_stream_trajectory,
)
from tpsr_ros.io.trajectory import Topics, read_trajectory

__all__ = [
    "add_topic_options",
    "read_training_bags",
    "register",
    "run",
    "summary_lines",
    "topics_from_args",
]


def add_topic_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--image-topic`` etc. from :class:`Topics` (None when not given: see topics_from_args)."""
    for f in dataclasses.fields(Topics):
        parser.add_argument(
            f"--{f.name}-topic",
            dest=f"{f.name}_topic",
            default=None,
            metavar="TOPIC",
            help=f"{f.metadata.get('help', '')} (default: {f.default}, or the model's)",
        )
    parser.add_argument(
        "--pose-frame",
        default=None,
        metavar="FRAME",
        help="with a tf2_msgs/TFMessage pose topic (/tf): the child frame whose transforms "
        f"are the ground truth (default: {DEFAULT_POSE_FRAME}, or the model's)",
    )


def register(subparsers: Any) -> None:
    """Add the ``fit`` subcommand."""
    doc = "learn a TPSR (guide chapter 3) or the PCA baseline from bags and write a model file"
    parser = subparsers.add_parser("fit", help=doc, description=doc[0].upper() + doc[1:] + ".")
    parser.add_argument("bags", nargs="+", type=Path, metavar="BAG", help="rosbag2 MCAP bag(s)")
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        metavar="MODEL",
        help="model file to write (.npz)",
    )
    parser.add_argument(
        "--method",
        choices=("tpsr", "pca"),
        default="tpsr",
        help="state model to learn (default: %(default)s)",
    )
    parser.add_argument(
        "--episodes",
        type=positive_int,
        default=None,
        metavar="N",
        help="use only the first N episodes (guide |E|: windows of m + 1 + n steps, one "
        "starting at every step under the default preset, so N of them span about N recorded "
        "steps, and every m + 1 + n steps under best and guide; default: all)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite an existing MODEL")
    parser.add_argument(
        "--init-from",
        type=Path,
        default=None,
        metavar="MODEL",
        help="refit on the bags with MODEL's whitenings, kernel centres and settings (its "
        "preset, sizes, topics and step grid; the rank follows the rank rule), the state "
        "coordinates rotated to MODEL's: the learner node's refit after MODEL, for a "
        "recording of its steps. TPSR options are refused with it",
    )
    parser.add_argument(
        "--forgetting",
        type=float,
        default=None,
        metavar="LAMBDA",
        help="with --init-from: weigh each episode by LAMBDA ** (its age in steps before the "
        "last step), in (0, 1], as the learner node's parameter forgetting does "
        "(default 1: every episode alike)",
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="CONFIG",
        help="TPSR parameters from a YAML file written by learner tune (options given "
        "here win over the file's)",
    )
    parameters = parser.add_argument_group("TPSR parameters (guide table 3.5)")
    add_preset_option(parameters, "fit")
    add_config_options(parameters, TPSRConfig, config_file=True)
    add_config_options(parser.add_argument_group("PCA baseline"), PCAConfig)
    add_topic_options(parser.add_argument_group("topics"))
    add_stream_options(
        parser.add_argument_group("robot bags: camera and commands resampled onto a step grid")
    )
    add_streamed_options(
        parser.add_argument_group(
            "streamed and distributed fit (memory bounded by chunk and centre counts)"
        )
    )
    parser.set_defaults(run=run)


def add_streamed_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--stream``, ``--chunk-steps``, ``--workers``, ``--scheduler`` and friends."""
    parser.add_argument(
        "--stream",
        action="store_true",
        help="read the bags twice in chunks instead of holding them in memory (the same "
        "spectral model to 1e-9; a refinement holds its steps in memory, at most "
        "tpsr.refine_steps, and its search follows the last bits of its start, so a refined "
        "model differs slightly; implied by --workers and --scheduler)",
    )
    parser.add_argument(
        "--chunk-steps",
        type=positive_int,
        default=DEFAULT_CHUNK_STEPS,
        metavar="N",
        help="steps per chunk of a streamed fit (default: %(default)s)",
    )
    parser.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        metavar="N",
        help="run the streamed fit on a local Dask cluster of N worker processes "
        "(needs the dask extra)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the streamed fit on the Dask cluster at ADDRESS (e.g. tcp://host:8786); "
        "its workers must see the bags at the same paths",
    )
    parser.add_argument(
        "--scheduler-timeout",
        type=positive_float,
        default=DEFAULT_TIMEOUT,
        metavar="SECONDS",
        help="give up on a scheduler that does not answer within this time (default: %(default)s)",
    )
    parser.add_argument(
        "--scratch-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="where a streamed fit keeps its temporary whitened episodes (248 bytes per "
        "episode with the default dimensions, 328 with --p-th-tests from-current; default: "
        "the system's temporary directory)",
    )


def _say(message: str) -> None:
    print(f"learner fit: {message}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Read bags, cut episodes, fit, write the model and print a summary."""
    output = check_output_path(args.output, force=args.force)
    file_values = None
    if args.config is not None:
        file_values, file_inputs = read_fit_file(args.config)
        if taken := apply_config_inputs(args, file_inputs):
            _say(f"options from {args.config}: {', '.join(taken)}")
    require_given_topics(args.bags, args)
    if args.init_from is not None:
        return _run_init_from(args, output)
    if args.forgetting is not None:
        raise ConfigError(
            "--forgetting weighs a refit's statistics: give the model to refit with --init-from"
        )
    stream_options = fit_options_from_args(args)
    # the options are checked before any bag is read (the preset's changes come after it)
    config_from_args(TPSRConfig, args, preset_from_args(args).tpsr_config(), file_values)
    # what the user set stays as set; the preset's sizes follow the data
    given = {f.name for f in dataclasses.fields(TPSRConfig) if getattr(args, f.name) is not None}
    args.sizing = Sizing(given | set(file_values or {}))
    pca_config = config_from_args(PCAConfig, args)
    topics = topics_from_args(args)
    if args.stream or args.workers is not None or args.scheduler is not None:
        return _run_streamed(args, output, file_values, pca_config, topics, stream_options)
    timings: dict[str, float] = {}

    _say(f"reading {len(args.bags)} bag(s)")
    start = time.perf_counter()
    trajectory, spec = read_training_bags(args, topics, stream_options)
    timings["reading bags"] = time.perf_counter() - start
    environment = trajectory.summary().get("environment")
    tpsr_config, record = _fit_config(args, file_values, spec, environment)
    episodes = make_episodes(
        trajectory,
        tpsr_config.history_length,
        tpsr_config.test_length,
        max_episodes=args.episodes,
        stride=tpsr_config.episode_stride,
    )
    _say(
        f"{len(trajectory)} steps in {len(trajectory.segment_bounds())} segment(s) -> "
        f"{len(episodes)} episodes"
    )
    start = time.perf_counter()
    model: StateModel
    pose_frame = _decoded_pose_frame(args, topics)
    if args.method == "tpsr":
        codes = None if spec is None else spec.codebook.codes  # action-aware features
        fitted = fit_trajectory(
            trajectory, tpsr_config, episodes=episodes, max_episodes=args.episodes,
            progress=_say, action_codes=codes, sizing=args.sizing, pose_frame=pose_frame,
        )  # fmt: skip
        model, tracked, view = fitted.model, fitted.tracked, fitted.view
        timings["fit"] = fitted.seconds
        _say_sizing(model)
    else:
        _say("PCA")
        model = fit_pca(episodes.steps(), n_actions=trajectory.n_actions, config=pca_config)
        timings["fit"] = time.perf_counter() - start
        tracked = track_trajectory(model, trajectory)  # once: the adequacy figures, the view
        view = view_of_track(tracked, trajectory, pose_frame)

    training = {
        **trajectory.summary(),
        "episodes": len(episodes),
        "max_episodes": args.episodes,
        "history_length": episodes.history_length,
        "test_length": episodes.test_length,
        "reading_seconds": round(timings["reading bags"], 6),
        "fit_seconds": round(timings["fit"], 6),
    }
    if isinstance(model, TPSRModel):  # enough data? episodes per action, recovery rate
        training["adequacy"] = _say_adequacy(assess(model, trajectory, tracked))
    _say_view(view)
    _write(model, output, training, spec, timings, preset=record, view=view, force=args.force)
    return 0


def _run_init_from(args: argparse.Namespace, output: Path) -> int:
    """``--init-from MODEL``: refit on the bags, read as MODEL's were, with its frozen basis."""
    given = [
        f"--{f.name.replace('_', '-')}"
        for f in dataclasses.fields(TPSRConfig)
        if getattr(args, f.name) is not None
    ]
    streamed = args.stream or args.workers is not None or args.scheduler is not None
    refused = given + (["--config"] if args.config is not None else [])
    refused += (["--method pca"] if args.method != "tpsr" else []) + (
        ["--episodes"] if args.episodes is not None else []
    )
    refused += ["--stream/--workers/--scheduler"] if streamed else []
    refused += ["--step-period"] if args.step_period is not None else []
    if refused:
        raise ConfigError(
            f"--init-from refits with {args.init_from}'s settings, whitenings and centres on "
            f"every step of the bags, in memory: {', '.join(refused)} cannot change them"
        )
    if args.forgetting is not None and not 0 < args.forgetting <= 1:
        raise ConfigError(f"--forgetting must lie in (0, 1], not {args.forgetting}")
    init = open_model(args.init_from)
    basis = init.model.basis if isinstance(init.model, TPSRModel) else None
    if basis is None:
        raise ConfigError(
            f"{args.init_from} holds no fit basis (a PCA model, or a TPSR written before "
            "models kept their whitenings and centres): fit it again with `learner fit`"
        )
    _say(f"reading {len(args.bags)} bag(s) as {args.init_from}'s were read")
    start = time.perf_counter()
    trajectory = read_for_model(init, args.bags, args)
    timings = {"reading bags": time.perf_counter() - start}
    spec = init.spec
    _say(f"{len(trajectory)} steps in {len(trajectory.segment_bounds())} segment(s)")
    pose_frame = init.view.pose_frame if init.view is not None else "map"
    start = time.perf_counter()
    forgetting = 1.0 if args.forgetting is None else args.forgetting
    fitted = fit_trajectory(
        trajectory, basis.config, basis=basis, progress=_say, pose_frame=pose_frame,
        action_codes=None if spec is None else spec.codebook.codes, forgetting=forgetting,
        align_to=init.model,
    )  # fmt: skip
    timings["fit"] = fitted.seconds
    _say_sizing(fitted.model)
    training = {
        **fitted.training(trajectory),
        "reading_seconds": round(timings["reading bags"], 6),
        "init_from": {"path": str(args.init_from), "fingerprint": init.fingerprint},
    }
    training["adequacy"] = _say_adequacy(assess(fitted.model, trajectory, fitted.tracked))
    _say_view(fitted.view)
    preset = init.metadata.get("preset")
    _write(
        fitted.model, output, training, spec, timings,
        preset=preset if isinstance(preset, dict) else None, view=fitted.view, force=args.force,
    )  # fmt: skip
    return 0


def _decoded_pose_frame(args: argparse.Namespace, topics: Topics) -> str:
    """The frame of the training poses (the decoded pose's): the first bag's, else ``map``."""
    if not topics.pose:
        return "map"
    child = args.pose_frame or DEFAULT_POSE_FRAME
    return pose_frame_id(args.bags[0], topics.pose, child) or "map"


def _say_view(view: ViewReadout) -> None:
    """Say what the viewer's read-outs (fitted on the training states) show."""
    pose = "" if view.pose is None else f" and the pose (frame {view.pose_frame})"
    _say(f"viewer read-outs: the next image for each action{pose}")


def _say_adequacy(adequacy: Adequacy) -> dict[str, Any]:
    """Say the recovery rate, and when the data are too little, why and what to record."""
    _say(
        f"tracking the training data {recovery_text(adequacy.recoveries, adequacy.steps)} "
        f"(recovery rate {adequacy.recovery_rate:.2f}); {adequacy.per_action:.1f} training "
        "episodes per action"
    )
    if (judgement := adequacy.judgement()) is not None:
        _say(f"warning: {judgement}")
    return adequacy.as_dict()


def read_training_bags(
    args: argparse.Namespace,
    topics: Topics,
    options: FitOptions | None,
    say: Callable[[str], None] = _say,
) -> tuple[Trajectory, StreamSpec | None]:
    """The steps of ``args.bags`` and, for robot bags (``options``), the spec they were read
    with: simulator bags paired by stamp, robot bags read once and resampled on the grid."""
    if options is None:
        return read_trajectory(args.bags, topics=topics), None
    pose_frame = args.pose_frame or DEFAULT_POSE_FRAME
    streams = read_bag_streams(  # once, for the spec and the steps
        args.bags,
        image_topic=topics.image,
        action_topic=topics.action,
        components=options.components,
        pose_topic=topics.pose,
        reward_topic=topics.reward,
        pose_frame=pose_frame,
    )
    spec = _robot_spec(args, options, topics, streams, say)
    prep = spec.preprocessing
    check_fit_memory(  # the batch fit holds every observation
        grid_step_count(streams, spec.grid), prep.height * prep.width * (1 if prep.grey else 3)
    )
    trajectory = read_stream_trajectory(
        args.bags,
        spec,
        pose_topic=topics.pose,
        reward_topic=topics.reward,
        pose_frame=pose_frame,
        streams=streams,
    )
    say(_commands_line(trajectory, spec))
    return trajectory, spec


def _robot_spec(
    args: argparse.Namespace,
    options: FitOptions,
    topics: Topics,
    streams: Sequence[BagStreams] | None = None,
    say: Callable[[str], None] = _say,
) -> StreamSpec:
    """Robot bags (``--step-period``): the step grid, preprocessing and codebook, said."""
    spec = fit_stream_spec(
        args.bags, options, image_topic=topics.image, action_topic=topics.action, streams=streams
    )
    say(_spec_line(spec, options))
    return spec


def _fit_config(
    args: argparse.Namespace,
    file_values: dict[str, Any] | None,
    spec: StreamSpec | None,
    environment: str | None,
) -> tuple[TPSRConfig, dict[str, Any] | None]:
    """The fit's parameters and the preset record of the model: the preset (with its robot
    bags' and turning robot's changes where the data are such), then the ``--config`` file's
    values, then the options (a robot turns: :func:`learner.inputs.robot_turns`)."""
    preset = preset_from_args(args)
    robot, turning = spec is not None, robot_turns(spec, environment)
    preset_config = preset.tpsr_config(robot=robot, turning=turning)
    tpsr_config = config_from_args(TPSRConfig, args, preset_config, file_values)
    if file_values is not None:
        _say(f"TPSR parameters from {args.config}: {describe(tpsr_config)}")
    if args.method != "tpsr":
        return tpsr_config, None
    _say_preset(preset, preset_config, tpsr_config, robot=robot, turning=turning)
    changed = departures(tpsr_config, preset_config)
    record = {"name": preset.name, "changed": changed}
    return tpsr_config, record | ({"turning": True} if turning and preset.turning_tpsr else {})


def _run_streamed(
    args: argparse.Namespace,
    output: Path,
    file_values: dict[str, Any] | None,
    pca_config: PCAConfig,
    topics: Topics,
    stream_options: FitOptions | None,
) -> int:
    """``--stream`` (and ``--workers`` / ``--scheduler``): the streamed fit, then as :func:`run`."""
    distributed = args.workers is not None or args.scheduler is not None
    if args.workers is not None and args.scheduler is not None:
        raise ConfigError("give --workers (a local cluster) or --scheduler, not both")
    if distributed and args.method == "pca":
        raise ConfigError(
            "the PCA baseline streams in one process only (one pass of moments): drop "
            "--workers/--scheduler or use --stream alone"
        )
    timings: dict[str, float] = {}
    start = time.perf_counter()
    pose_frame = args.pose_frame or DEFAULT_POSE_FRAME
    recorded = dataclasses.asdict(topics)
    spec = None
    if stream_options is not None:
        spec = _robot_spec(args, stream_options, topics)
    if spec is None:
        _say(f"checking {len(args.bags)} bag(s) agree (image size, action type)")
        surveys = survey_bags(args.bags, topics)
        environment = common_value(s.environment for s in surveys)
        vertical_half_extent = common_value(s.vertical_half_extent for s in surveys)
        image_shape = list(surveys[0].image_size)
    else:  # robot bags: the spec reads every bag's commands; then each bag is read whole
        environment = vertical_half_extent = None
        image_shape = [spec.preprocessing.height, spec.preprocessing.width]
        recorded["pose_frame"] = pose_frame  # as the in-memory fit records it
    tpsr_config, preset = _fit_config(args, file_values, spec, environment)
    reader = BagChunks(
        topics=topics, chunk_steps=args.chunk_steps, spec=spec, pose_frame=pose_frame
    )
    timings["reading bags"] = time.perf_counter() - start
    start = time.perf_counter()
    m, n = tpsr_config.history_length, tpsr_config.test_length
    model: StateModel
    if args.method == "pca":
        _say("PCA (streamed, one pass)")
        model = fit_pca_streamed(
            lambda: reader.read_all(args.bags),
            config=pca_config,
            history_length=m,
            test_length=n,
            max_episodes=args.episodes,
            stride=tpsr_config.episode_stride,
        )
        episodes = int(model.fit_info["observations"]) // tpsr_config.window_steps
    else:
        fit = functools.partial(
            fit_tpsr_streamed,
            config=tpsr_config,
            max_episodes=args.episodes,
            progress=_say,
            scratch_dir=args.scratch_dir,
            sizing=args.sizing,
        )
        if distributed:
            if tpsr_config.refine_epochs:  # refuse now, not after the cluster's passes
                check_bags_readable_here(
                    args.bags,
                    "the refinement reads its steps here, not on the cluster's workers: "
                    "mount them here, or add --refine-epochs 0",
                )
            where = args.scheduler or f"a local cluster of {args.workers} worker(s)"
            _say(f"connecting to {where}")
            with dask_client(
                scheduler=args.scheduler, workers=args.workers, timeout=args.scheduler_timeout
            ) as client:
                check_bags_visible(client, args.bags)
                model = fit(  # the refinement's steps are read here, in bag order
                    DaskEngine(client, args.bags, reader),
                    refine_source=lambda: reader.read_all(args.bags),
                )
        else:
            model = fit(lambda: reader.read_all(args.bags))
        episodes = int(model.fit_info["episodes"])
        _say_sizing(model)
    timings["fit"] = time.perf_counter() - start
    info = model.fit_info
    training = {
        "bags": [{"path": str(bag), "topics": recorded} for bag in args.bags],
        "steps": info["steps"],
        "segments": info["segments"],
        "stamps_ns": info["stamps_ns"],
        "environment": environment,
        "vertical_half_extent": vertical_half_extent,
        "image_shape": image_shape,
        "episodes": episodes,
        "max_episodes": args.episodes,
        "history_length": m,
        "test_length": n,
        "streamed": {"chunk_steps": args.chunk_steps, "workers": args.workers,
                     "scheduler": args.scheduler},
        "reading_seconds": round(timings["reading bags"], 6),
        "fit_seconds": round(timings["fit"], 6),
    }  # fmt: skip
    start = time.perf_counter()
    try:
        view: ViewReadout | None = _streamed_view(
            model, reader.read_all(args.bags), int(info["steps"]),
            _decoded_pose_frame(args, topics),
        )  # fmt: skip
    except TpsrError as exc:  # e.g. bags only the cluster's workers can read
        view = None
        _say(f"no viewer read-outs (the filter node will publish no view topics): {exc}")
    timings["viewer read-outs"] = time.perf_counter() - start
    _write(model, output, training, spec, timings, preset=preset, view=view, force=args.force)
    return 0


def _streamed_view(
    model: StateModel, chunks: Iterator[Trajectory], total_steps: int, pose_frame: str
) -> ViewReadout:
    """The viewer's read-outs in one more pass over the chunks, in this process: each chunk
    tracked on from its segment's last state in the previous one, its sums added (the
    same read-outs as in memory, to rounding)."""
    rows = point_rows(total_steps)
    sums: ViewSums | None = None
    before: tuple[np.ndarray, int] | None = None
    points, offset = [], 0
    for chunk in chunks:
        if sums is None:
            sums = ViewSums(chunk.n_actions, model.state_dim, model.obs_size,
                            chunk.positions.shape[1])  # fmt: skip
        states = np.empty((len(chunk), model.state_dim))
        for a, b in chunk.segment_bounds():
            carried = before is not None and a == 0 and chunk.segments[0] == before[1]
            initial = before[0] if carried and before is not None else None
            states[a:b] = model.track(chunk.actions[a:b], chunk.observations[a:b], initial).states
        sums.add(states, chunk.actions, chunk.observations, chunk.segments, chunk.positions,
                 before)  # fmt: skip
        mine = rows[(rows >= offset) & (rows < offset + len(chunk))]
        points.append(states[mine - offset])
        offset += len(chunk)
        before = (states[-1], int(chunk.segments[-1]))
    if sums is None:
        raise ConfigError("the bags hold no steps for the viewer's read-outs")
    view = sums.solve(np.concatenate(points), pose_frame)
    pose = "" if view.pose is None else f" and the pose (frame {pose_frame})"
    _say(f"viewer read-outs (one more pass): the next image for each action{pose}")
    return view


def _say_sizing(model: StateModel) -> None:
    """Say which sizes the fit lowered to what the data carry (:mod:`tpsr_ros.core.sizing`)."""
    sized = model.fit_info.get("sized") if isinstance(model, TPSRModel) else None
    if sized:
        changes = {name: (int(old), int(new)) for name, (old, new) in sized.items()}
        by_rule = changes.get("rank", (0, 0))[1] == model.fit_info.get("supported_rank")
        n_train = int(model.fit_info["independent_episodes"]) if by_rule else None
        _say(describe_sizing(int(model.fit_info["episodes"]), changes, n_train))


def _say_preset(
    preset: Preset, preset_config: TPSRConfig, config: TPSRConfig, *, robot: bool, turning: bool
) -> None:
    """Say which preset the fit starts from and what the options changed in it."""
    changed = departures(config, preset_config)
    extras = [
        f"{what} settings ({' '.join(f'{k}={v}' for k, v in changes.items())})"
        for what, applies, changes in (
            ("robot-bag", robot, preset.robot_tpsr),
            ("turning robot's", turning, preset.turning_tpsr),
        )
        if applies and changes
    ]
    with_extras = f" with its {' and '.join(extras)}" if extras else ""
    what = " ".join(f"{k}={v}" for k, v in changed.items()) or "nothing"
    _say(f"preset {preset.name}{with_extras} ({preset.summary}); changed by options: {what}")


def _write(
    model: StateModel,
    output: Path,
    training: dict[str, Any],
    spec: StreamSpec | None,
    timings: dict[str, float],
    *,
    preset: dict[str, Any] | None,
    force: bool,
    view: ViewReadout | None = None,
) -> None:
    """Write the model file, then print the summary (with the time writing took)."""
    _say(f"writing {output}")
    start = time.perf_counter()
    save_model(
        model, output, training=training, inputs=spec, preset=preset, view=view, force=force
    )
    timings["writing"] = time.perf_counter() - start
    for line in summary_lines(model, training, timings, output):
        print(line)


def _spec_line(spec: StreamSpec, options: FitOptions | None = None) -> str:
    """The spec in one line; with ``options``, which values are defaults sized to the data."""
    prep, grid = spec.preprocessing, spec.grid.as_dict()
    phase = grid.get("phase_s")
    kmeans = spec.codebook.kind == "kmeans"
    defaults = {
        "phase": options is not None and options.step_offset is None,
        "image": options is not None and options.image_size is None,
        "actions": options is not None and options.actions is None and kmeans,
    }
    return (
        f"steps of {grid['step_period_s']:g} s"
        + ("" if phase is None else f", offset {phase:.3f} s")
        + (" (chosen to keep steps clear of stamps; --step-offset to set)"
           if defaults["phase"] else "")
        + f" (camera period {grid['camera_period_s']:.3g} s, images used up to "
        f"{grid['image_timeout_s']:.3g} s old); "
        f"observations {prep.width}x{prep.height} {'grey' if prep.grey else 'colour'}"
        + (" (default; --image-size to set)" if defaults["image"] else "")
        + f"; {len(spec.codebook)} actions over {', '.join(spec.codebook.components)} "
        f"({spec.codebook.kind})"
        + (" (default sized to the steps and the commands' clusters; --actions to set)"
           if defaults["actions"] else "")
    )  # fmt: skip


def _commands_line(trajectory: Trajectory, spec: StreamSpec) -> str:
    return far_commands_line(trajectory, spec)


def _fmt(values: Any) -> str:
    return " ".join(f"{v:.4g}" for v in np.asarray(values, dtype=float).ravel())


def summary_lines(
    model: StateModel, training: dict[str, Any], timings: dict[str, float], output: Path
) -> list[str]:
    """Human-readable summary of a fit."""
    lines = [
        f"model: {output} (method {model.method}, state dimension {model.state_dim}, "
        f"{model.n_actions} actions)",
        f"data: {len(training.get('bags', []))} bag(s), {training.get('steps')} steps, "
        f"{training.get('segments')} segment(s), {training.get('episodes')} episodes, "
        f"{environment_label(training.get('environment'))}",
    ]
    if isinstance(model, TPSRModel):
        r = model.state_dim
        sv = model.singular_values
        lines.append(
            f"training episodes after {max(model.config.obs_centers, model.config.ht_centers)} "
            f"kernel centres: {model.fit_info.get('training_episodes')}"
            if model.config.center_selection == "first"
            else f"training episodes: {model.fit_info.get('training_episodes')}"
        )
        lines.append(f"singular values of P_TH: kept {_fmt(sv[:r])} | next {_fmt(sv[r:])}")
        ev = model.explained_variance
        lines.append(
            "whitening explained variance: "
            + ", ".join(f"{key} {val.sum():.3f} ({val.size} dims)" for key, val in ev.items())
        )
        if kernel := model.fit_info.get("obs_kernel"):
            lines.append(kernel_line(kernel, model.obs_centers.shape[0]))
        if refined := model.fit_info.get("refinement"):
            lines.append(refinement_line(refined, timings["fit"]))
        stages = model.fit_info.get("timings", {})
    elif isinstance(model, PCAModel):
        ratio = model.explained_variance_ratio
        lines.append(f"explained variance: {ratio.sum():.3f} ({_fmt(ratio)})")
        stages = model.fit_info.get("timings", {})
    else:  # pragma: no cover - future methods
        stages = {}
    parts = [f"reading bags {timings['reading bags']:.2f} s"]
    parts += [f"{name} {sec:.3f} s" for name, sec in stages.items()]
    parts += [f"fit total {timings['fit']:.2f} s", f"writing {timings['writing']:.2f} s"]
    lines.append("timing: " + "; ".join(parts))
    return lines


def refinement_line(refined: dict[str, Any], fit_seconds: float) -> str:
    """What the refinement through the filter did, and its share of the fit's time."""
    kept = (
        "the spectral model kept (no iterate predicted better without restarting more)"
        if refined["best_iteration"] == 0
        else f"best after iteration {refined['best_iteration']}"
    )
    carry = refined.get("carry", 0.0)
    start = f" from a start carrying {carry:g} of the state" if carry else ""
    if "history_gain" in refined:  # refine_carry_rule aliased chose the carry
        start += (
            f" (the previous image's held-out gain in predicting the next ones "
            f"{refined['history_gain']:+.4f}{'' if carry else ': no carry'})"
        )
    restarts = (
        f"; held-out restarts {refined['heldout_restarts']} (allowed "
        f"{refined['heldout_restarts_allowed']})"
        if "heldout_restarts" in refined
        else ""
    )
    share = 100.0 * refined["seconds"] / fit_seconds if fit_seconds > 0 else 0.0
    return (
        f"refinement{start}: {refined['iterations']} iteration(s), {kept}; held-out "
        f"unexplained variance of {predicted_images(refined)} "
        f"{refined['heldout_unexplained_spectral']:.4f}"
        f" -> {refined['heldout_unexplained']:.4f}{restarts}; {refined['seconds']:.1f} s "
        f"({share:.0f} % of the fit)"
    )
