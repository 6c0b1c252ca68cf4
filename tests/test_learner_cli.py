"""``python -m learner fit | info | plot``: options, outputs, one-line errors, and the
full-environment check that tracked states are linearly predictive of the true position."""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from cli_support import run_entry

from learner.cli import SUBCOMMANDS, build_parser, main
from learner.options import config_from_args
from learner.plots import affine_r2
from learner.simulated import random_trajectory
from sim_node import SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.core.episodes import track_trajectory
from tpsr_ros.core.pca_baseline import PCAModel
from tpsr_ros.core.presets import PRESETS
from tpsr_ros.core.tpsr import TPSRConfig, TPSRModel
from tpsr_ros.io.model_io import load_model, read_metadata

SMALL_OPTIONS = ["--obs-centers", "40", "--ht-centers", "80", "--rank", "3"]


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bags") / "small"
    generate_bag(path, SimConfig(environment="full"), 900, seed=3)
    return path


def test_every_table_3_5_parameter_is_an_option():
    fit = build_parser()._subparsers._group_actions[0].choices["fit"]
    options = {s for a in fit._actions for s in a.option_strings}
    for name in (
        "--history-length",
        "--test-length",
        "--obs-dim",
        "--ht-dim",
        "--obs-centers",
        "--ht-centers",
        "--sigma-obs",
        "--sigma-ht",
        "--rank",
        "--centers",
        "--seed",
        "--episodes",
        "--method",
        "--force",
        "--pca-dim",
        "--image-topic",
        "-o",
    ):
        assert name in options, name
    actions = {a.dest: a for a in fit._actions}
    best, guide = PRESETS["predictive"], PRESETS["guide"]  # the default preset, the guide's
    for f in dataclasses.fields(TPSRConfig):
        # resolved at run time (None here): an option given wins over a --config file's
        # value, which wins over the preset's (with its robot-bag settings), then the config's
        assert actions[f.name].default is None, f.name
        help_text = actions[f.name].help
        assert str(getattr(best.tpsr_config(), f.name)) in help_text and "--config" in help_text
        assert str(f.default) in help_text, f.name  # the guide's value, the dataclass default
    assert actions["preset"].default == "predictive"
    args = fit.parse_args(["bag", "-o", "model.npz"])
    assert config_from_args(TPSRConfig, args) == TPSRConfig()
    assert config_from_args(TPSRConfig, args, best.tpsr_config()) == best.tpsr_config()
    robot = config_from_args(TPSRConfig, args, guide.tpsr_config(robot=True))
    assert robot == TPSRConfig(normalize_ht_features=True)
    from_file = config_from_args(TPSRConfig, args, guide.tpsr_config(robot=True), {"rank": 3})
    assert from_file == TPSRConfig(rank=3, normalize_ht_features=True)
    given = fit.parse_args(["bag", "-o", "m.npz", "--rank", "4", "--no-normalize-ht-features"])
    mixed = config_from_args(TPSRConfig, given, best.tpsr_config(), {"rank": 3})
    assert mixed == best.tpsr_config(rank=4, normalize_ht_features=False)


@pytest.mark.slow
def test_fit_info_plot(small_bag, tmp_path, capsys):
    model_path = tmp_path / "m.npz"
    assert (
        main(
            [
                "fit",
                str(small_bag),
                "-o",
                str(model_path),
                *SMALL_OPTIONS,
                "--sigma-ht",
                "3.0",
                "--episodes",
                "250",
                "--preset",
                "best",
            ]
        )
        == 0
    )
    out, err = capsys.readouterr()
    assert "singular values of P_TH: kept" in out and "whitening explained variance" in out
    assert "timing: reading bags" in out and "whitening" in out
    for stage in ("reading 1 bag(s)", "whitening", "features", "SVD", "writing"):
        assert stage in err
    assert "preset best" in err  # the fit says which preset it starts from
    model = load_model(model_path)
    assert isinstance(model, TPSRModel)
    expected = PRESETS["best"].tpsr_config(obs_centers=40, ht_centers=80, rank=3, sigma_ht=3.0)
    # obs_variance 0.95 chooses d^O from the data; the model records the choice
    assert model.config == dataclasses.replace(expected, obs_dim=model.config.obs_dim)
    assert model.config.obs_dim != expected.obs_dim
    meta = read_metadata(model_path)
    assert meta["preset"]["name"] == "best"
    assert meta["preset"]["changed"] == {"obs_centers": 40, "ht_centers": 80, "rank": 3,
                                         "sigma_ht": 3.0}
    assert meta["training"]["episodes"] == 250 and meta["training"]["steps"] == 900
    assert meta["training"]["environment"] == "full"
    assert meta["training"]["bags"][0]["generator"]["seed"] == 3
    assert meta["training"]["bags"][0]["topics"]["image"] == "/camera/image_raw"

    assert main(["info", str(model_path)]) == 0
    out, _ = capsys.readouterr()
    assert "method: tpsr, state dimension 3, 25 actions" in out and "rank=3" in out
    changed = "obs_centers=40, ht_centers=80, sigma_ht=3.0, rank=3"
    assert f"preset: best; changed by options: {changed}" in out

    png = tmp_path / "states.png"
    assert main(["plot", str(model_path), str(small_bag), "-o", str(png)]) == 0
    out, _ = capsys.readouterr()
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert "R^2 of true position" in out


@pytest.mark.slow
def test_pca_method(small_bag, tmp_path, capsys):
    path = tmp_path / "p.npz"
    assert main(["fit", str(small_bag), "-o", str(path), "--method", "pca", "--pca-dim", "3"]) == 0
    assert "explained variance" in capsys.readouterr().out
    model = load_model(path)
    assert isinstance(model, PCAModel) and model.state_dim == 3
    assert main(["plot", str(path), str(small_bag), "-o", str(tmp_path / "p.png")]) == 0


def test_errors_are_one_line_and_write_nothing(small_bag, tmp_path, capsys):
    out_path = tmp_path / "m.npz"
    code, _, err = run_entry(
        ["fit", str(small_bag), "-o", str(out_path), *SMALL_OPTIONS, "--rank", "500"], capsys
    )
    assert code == 1 and err.count("\n") == 1 and err.startswith("learner: error: ")
    assert "Traceback" not in err and not out_path.exists()
    code, _, err = run_entry(  # sizes set on purpose are kept, and refused if too large
        ["fit", str(small_bag), "-o", str(out_path), "--episodes", "100", "--ht-centers", "1000"],
        capsys,
    )
    assert code == 1 and "too few for 1000 kernel centres" in err and not out_path.exists()
    code, _, err = run_entry(["fit", str(tmp_path / "nope"), "-o", str(out_path)], capsys)
    assert code == 1 and "not a rosbag2 directory" in err
    code, _, err = run_entry(["fit", str(small_bag), "-o", str(out_path), "--rank", "abc"], capsys)
    assert code == 2 and err.startswith("learner fit: error: ") and err.count("\n") == 1
    out_path.write_bytes(b"keep me")
    code, _, err = run_entry(["fit", str(small_bag), "-o", str(out_path)], capsys)
    assert code == 1 and "use --force" in err and out_path.read_bytes() == b"keep me"
    code, _, err = run_entry(["info", str(out_path)], capsys)
    assert code == 1 and "truncated or foreign" in err


def test_the_presets_sizes_follow_the_data_and_the_fit_says_so(small_bag, tmp_path, capsys):
    out_path = tmp_path / "m.npz"
    code, _, err = run_entry(["fit", str(small_bag), "-o", str(out_path), "--episodes", "300"],
                             capsys)
    assert code == 0, err
    assert "300 episodes carry less than configured: ht_centers 1000 -> 150, obs_centers 500 " \
        "-> 150" in err
    model = load_model(out_path)
    assert (model.config.ht_centers, model.config.obs_centers, model.config.rank) == (150, 150, 8)
    assert model.fit_info["sized"] == {"ht_centers": [1000, 150], "obs_centers": [500, 150]}


def test_python_dash_m_entry_point(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "learner", "info", str(tmp_path / "x.npz")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1
    assert (
        proc.stderr.strip()
        == f"learner: error: model file {str(tmp_path / 'x.npz')!r} does not exist"
    )


def _subcommands(command: str | None = None) -> list[str]:
    """The commands ``build_parser(command)`` mounts, in its order."""
    (commands,) = (
        a for a in build_parser(command)._actions if isinstance(a, argparse._SubParsersAction)
    )  # fmt: skip
    return list(commands.choices)


def test_each_command_is_the_one_its_module_adds_and_starts_without_the_others():
    """The table names every command by what its module registers, in order; a command
    builds its parser from its own module, and starting ``fit`` loads neither the results
    page nor SciPy's statistics (what ``report`` and the studies need)."""
    assert _subcommands() == list(SUBCOMMANDS)
    for command in SUBCOMMANDS:
        assert _subcommands(command) == [command]
    code = (
        "import sys; from learner.cli import main\n"
        "try:\n    main(['fit', '--help'])\nexcept SystemExit:\n    pass\n"
        "print(sorted(m for m in ('learner.results_page', 'learner.report', 'scipy.stats') "
        "if m in sys.modules))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert proc.stdout.strip().splitlines()[-1] == "[]"


@pytest.mark.parametrize("command", _subcommands())
def test_every_subcommand_prints_its_help(command, capsys):
    """argparse expands ``%`` in help strings: a stray one breaks ``--help`` of a command."""
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    usage = capsys.readouterr().out.splitlines()[0]
    assert usage.startswith("usage: ") and command in usage


# --- the full environment (guide figure 4.5 settings) -------------------------------------


@pytest.fixture(scope="module")
def full_bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("full")
    train = root / "train24000"
    generate_bag(train, SimConfig(environment="full"), 24_000, seed=0)
    # the states scored on: the steps a 5000-step bag of seed 1 holds (read back, every array
    # is equal), simulated without writing and reading the bag
    return train, random_trajectory("full", 5000, seed=1)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("options", "minimum", "training"),
    [
        (["--preset", "guide"], 0.6, 7000),  # sigma_h/t 2.0: x ~0.7, y ~0.8 on our simulator
        (["--preset", "guide", "--sigma-ht", "4.0"], 0.8, 7000),  # the guide's range 2-6 (4.3)
        (["--preset", "best"], 0.9, 8000),  # k-means centres train on every episode
    ],
    ids=["guide", "guide-sigma-ht-4", "best"],
)
def test_full_environment_states_predict_position(
    full_bags, tmp_path, capsys, options, minimum, training
):
    train, rl = full_bags
    model_path = tmp_path / "full.npz"
    assert main(["fit", str(train), "-o", str(model_path), *options]) == 0
    capsys.readouterr()
    model = load_model(model_path)
    assert model.fit_info["training_episodes"] == training
    tracked = track_trajectory(model, rl)
    r2 = affine_r2(tracked.states, rl.positions)
    with capsys.disabled():
        print(
            f"\n[full environment, learner fit {' '.join(options) or 'defaults'}] R^2 of true "
            f"(x, y) from tracked states: {r2.round(3).tolist()}, recoveries "
            f"{int(tracked.recovered.sum())} of {len(rl)}"
        )
    assert (r2 >= minimum).all(), r2
    assert tracked.recovered.mean() < 0.01
    # the filter node's streaming update agrees with batch tracking on a recorded bag
    state = model.initial_state()
    for s in range(300):
        state, _ = model.update(state, int(rl.actions[s]), rl.observations[s])
        np.testing.assert_array_equal(state, tracked.states[s])
