"""``learner fit --stream / --workers / --scheduler``: the same model from bags, and bad input."""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import socket
import types
import warnings

import numpy as np
import pytest
from cli_support import run_entry

from learner.distributed import SCHEDULER_HTTP
from sim_node import SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.core.episodes import make_episodes
from tpsr_ros.core.errors import BagError, ConfigError
from tpsr_ros.core.pca_baseline import fit_pca
from tpsr_ros.core.presets import PRESETS
from tpsr_ros.core.streamed_fit import fit_pca_streamed, fit_tpsr_streamed
from tpsr_ros.core.tpsr import TPSRConfig, fit_tpsr_episodes
from tpsr_ros.io.bag_chunks import BagChunks, survey_bags
from tpsr_ros.io.model_io import load_model, read_metadata
from tpsr_ros.io.trajectory import read_trajectory

SMALL = ["--preset", "best", "--obs-centers", "40", "--ht-centers", "80", "--rank", "3"]
CONFIG = PRESETS["best"].tpsr_config(obs_centers=40, ht_centers=80, rank=3)  # the CLI's
ARRAYS = ("obs_mean", "obs_whitening", "obs_centers", "b_star", "b_inf", "B", "singular_values")


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("stream_bags")
    paths = [root / "a", root / "b"]
    generate_bag(paths[0], SimConfig(environment="full"), 700, seed=3)
    generate_bag(paths[1], SimConfig(environment="full"), 500, seed=4)
    return paths


@pytest.fixture(scope="module")
def reference(bags):
    return fit_tpsr_episodes(make_episodes(read_trajectory(bags), 1, 1), config=CONFIG)


def assert_same(model, reference, tol=1e-9):
    for name in ARRAYS:
        a, b = getattr(model, name), getattr(reference, name)
        assert a.shape == b.shape
        assert np.abs(a - b).max() <= tol * np.abs(b).max(), name


@pytest.mark.slow
def test_stream_option_writes_the_in_memory_model(bags, reference, tmp_path, capsys):
    out = tmp_path / "m.npz"
    code, stdout, stderr = run_entry(
        ["fit", *map(str, bags), "-o", str(out), "--stream", "--chunk-steps", "97", *SMALL],
        capsys,
    )
    assert code == 0, stderr
    assert "pass 1: whitening statistics" in stderr and "pass 2" in stderr
    assert "1200 steps, 2 segment(s), 399 episodes" in stdout
    assert_same(load_model(out), reference)
    training = read_metadata(out)["training"]  # what the filter node and `info` read
    assert training["image_shape"] == [16, 16] and training["environment"] == "full"
    pca, pca_in_memory = tmp_path / "pca.npz", tmp_path / "pca_memory.npz"
    for path, streamed in ((pca, ["--stream"]), (pca_in_memory, [])):
        code, stdout, stderr = run_entry(
            ["fit", *map(str, bags), "-o", str(path), *streamed, "--method", "pca"], capsys
        )
        assert code == 0, stderr
        # the default preset's windows start at every step: 1200 - 2 x (2 + 1) of them
        assert "1200 steps, 2 segment(s), 1194 episodes" in stdout
    streamed_pca, in_memory_pca = load_model(pca), load_model(pca_in_memory)
    for name in ("mean", "components", "eigenvalues"):
        np.testing.assert_allclose(
            getattr(streamed_pca, name), getattr(in_memory_pca, name), rtol=1e-9, atol=1e-12
        )


EVERY_OPTION = [*SMALL, "--history-length", "2", "--test-length", "2", "--history-action-weight",
                "1", "--test-action-weight", "0.5", "--state-clip-quantile", "0.05"]
"""Options the streamed fit once refused: action-aware features and the state box."""


STREAMED = [["--stream", "--chunk-steps", "150"], ["--workers", "1"]]
"""The two ways of streaming a fit: in this process, and on a Dask cluster."""


def fit_in_memory(bags, directory, options):
    """The in-memory model of ``learner fit`` with ``options``: the reference of each way of
    streaming it."""
    from learner.cli import main

    memory = directory / "memory.npz"
    assert main(["fit", *map(str, bags), "-o", str(memory), *options]) == 0
    return load_model(memory)


@pytest.fixture(scope="module")
def every_option_in_memory(bags, tmp_path_factory):
    return fit_in_memory(bags, tmp_path_factory.mktemp("every_option"), EVERY_OPTION)


@pytest.mark.slow
@pytest.mark.parametrize("how", STREAMED)
def test_every_fit_option_streams_and_distributes(
    bags, every_option_in_memory, tmp_path, capsys, how
):
    """Options the streamed fit once refused (action-aware features, the state box) give
    the in-memory model streamed and on Dask too."""
    if "--workers" in how:
        pytest.importorskip("distributed")
    other = tmp_path / "other.npz"
    argv = ["fit", *map(str, bags), "-o", str(other), *EVERY_OPTION, *how]
    code, _, err = run_entry(argv, capsys)
    assert code == 0, err
    streamed, reference = load_model(other), every_option_in_memory
    assert_same(streamed, reference)
    assert np.abs(streamed.state_box - reference.state_box).max() <= 1e-9 * np.abs(
        reference.state_box
    ).max()


PREDICTIVE = [*SMALL, "--preset", "predictive", "--refine-epochs", "3"]
"""The predictive preset (overlapping episodes, refinement), which the streamed fit once
refused."""


@pytest.fixture(scope="module")
def predictive_in_memory(bags, tmp_path_factory):
    return fit_in_memory(bags, tmp_path_factory.mktemp("predictive"), PREDICTIVE)


@pytest.mark.slow
@pytest.mark.parametrize("how", STREAMED)
def test_the_predictive_preset_streams_and_distributes(
    bags, predictive_in_memory, tmp_path, capfd, how
):
    """Overlapping episodes are cut across chunks and the refinement reads its steps once
    more, in this process: on these small bags, the in-memory model to 1e-6."""
    if "--workers" in how:
        pytest.importorskip("distributed")
    out = tmp_path / "streamed.npz"
    argv = ["fit", *map(str, bags), "-o", str(out), *PREDICTIVE, *how]
    code, stdout, err = run_entry(argv, capfd)
    assert code == 0, err
    assert "reading the steps to refine on (at most 50000)" in err
    assert "1200 steps, 2 segment(s), 1194 episodes" in stdout  # every window of each bag
    streamed = load_model(out)
    assert streamed.fit_info["refinement"]["iterations"] >= 1
    assert_same(streamed, predictive_in_memory, tol=1e-6)


@pytest.mark.slow
def test_streamed_pca_baseline_equals_fit_pca(bags):
    reader = BagChunks(chunk_steps=111)
    episodes = make_episodes(read_trajectory(bags), 1, 1)
    whole = fit_pca(episodes.steps(), n_actions=25)
    streamed = fit_pca_streamed(lambda: reader.read_all(bags))
    for name in ("mean", "components", "eigenvalues", "explained_variance_ratio"):
        a, b = getattr(streamed, name), getattr(whole, name)
        assert np.abs(a - b).max() <= 1e-9 * np.abs(b).max(), name


@pytest.mark.slow
def test_dask_local_cluster_equals_one_process(bags, reference, monkeypatch):
    """Rows stay on the workers: the client holds only the 'first' centres' rows."""
    distributed = pytest.importorskip("distributed")
    import learner.distributed
    from learner.distributed import DaskEngine, check_bags_visible

    first = TPSRConfig(obs_centers=40, ht_centers=80, rank=3)  # the guide's 'first' centres
    kmeans = dataclasses.replace(first, center_selection="kmeans")

    reader = BagChunks(chunk_steps=512)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
            scheduler_kwargs=SCHEDULER_HTTP,
        ) as cluster,
        distributed.Client(cluster, set_as_default=False) as client,
    ):
        check_bags_visible(client, bags)
        engine = DaskEngine(client, bags, reader)
        model = fit_tpsr_streamed(engine, config=first)
        limited = fit_tpsr_streamed(engine, config=first, max_episodes=230)  # bag b left out
        with_kmeans = fit_tpsr_streamed(engine, config=kmeans)  # the client gathers every row
        monkeypatch.setattr(learner.distributed, "MAX_SHIPPED_P_TH_BYTES", 0)
        p_th_here = fit_tpsr_streamed(engine, config=first)  # P_TH summed in the client
        with pytest.raises(ConfigError, match=r"cannot see bag\(s\)"):
            check_bags_visible(client, [*bags, bags[0].parent / "elsewhere"])
    assert model.fit_info["streamed"]["engine"].startswith("dask, 2 worker(s)")
    assert_same(model, fit_tpsr_episodes(make_episodes(read_trajectory(bags), 1, 1), config=first))
    one_process = fit_tpsr_streamed(lambda: reader.read_all(bags), config=first)
    assert_same(model, one_process)
    assert_same(p_th_here, one_process)
    row_bytes = one_process.fit_info["streamed"]["scratch_bytes"] // 399  # 248: 3 x 10 + 1
    assert row_bytes == 8 * (3 * 10 + 1)
    centre_rows = max(first.ht_centers, first.obs_centers)
    assert model.fit_info["streamed"]["scratch_bytes"] == centre_rows * row_bytes
    assert with_kmeans.fit_info["streamed"]["scratch_bytes"] == 399 * row_bytes
    assert_same(with_kmeans, fit_tpsr_streamed(lambda: reader.read_all(bags), config=kmeans))
    first_230 = make_episodes(read_trajectory(bags), 1, 1, max_episodes=230)
    assert_same(limited, fit_tpsr_episodes(first_230, config=first))


@pytest.mark.slow
def test_a_scheduler_that_does_not_answer_is_one_line(bags, tmp_path, capsys):
    pytest.importorskip("distributed")
    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    out = tmp_path / "m.npz"
    argv = ["fit", str(bags[0]), "-o", str(out), "--scheduler", f"tcp://127.0.0.1:{port}"]
    code, _, stderr = run_entry([*argv, "--scheduler-timeout", "0.5", *SMALL], capsys)
    assert code == 1
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("learner: error: no Dask scheduler answers at")
    assert f"127.0.0.1:{port}" in last and "within 0.5 s" in last
    assert "Traceback" not in stderr and not out.exists()


def test_a_bag_that_vanishes_mid_fit_fails_naming_it_and_writes_nothing(
    bags, tmp_path, capsys, monkeypatch
):
    doomed = tmp_path / "doomed"
    shutil.copytree(bags[1], doomed)
    original = BagChunks.read_all
    calls = []

    def read_all(self, paths):
        calls.append(1)
        if len(calls) == 2:  # the second pass: the bag is gone
            shutil.rmtree(doomed)
        return original(self, paths)

    monkeypatch.setattr(BagChunks, "read_all", read_all)
    out = tmp_path / "m.npz"
    code, _, stderr = run_entry(
        ["fit", str(bags[0]), str(doomed), "-o", str(out), "--stream", *SMALL], capsys
    )
    assert code == 1 and len(calls) == 2
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("learner: error:") and str(doomed) in last
    assert not out.exists()


def test_bags_with_other_images_are_refused_before_the_first_pass(bags, tmp_path, capsys):
    small = tmp_path / "eight"
    generate_bag(small, SimConfig(environment="full", image_size=8), 40, seed=5)
    with pytest.raises(BagError, match="cannot be fitted together: images 16x16 rgb8 vs 8x8"):
        survey_bags([bags[0], small])
    out = tmp_path / "m.npz"
    argv = ["fit", str(bags[0]), str(small), "-o", str(out), "--stream"]
    code, _, stderr = run_entry(argv, capsys)
    assert code == 1 and "pass 1" not in stderr and not out.exists()
    assert str(small) in stderr.strip().splitlines()[-1]


def test_option_conflicts_are_one_line(bags, tmp_path, capsys):
    out = str(tmp_path / "m.npz")
    code, _, stderr = run_entry(
        ["fit", str(bags[0]), "-o", out, "--workers", "1", "--scheduler", "tcp://x:1"], capsys
    )
    assert code == 1 and "not both" in stderr
    code, _, stderr = run_entry(
        ["fit", str(bags[0]), "-o", out, "--method", "pca", "--workers", "1"], capsys
    )
    assert code == 1 and "PCA baseline streams in one process only" in stderr


@pytest.mark.slow
def test_robot_bags_stream_on_their_step_grid(bags, tmp_path, capsys):
    """--step-period: each bag is read whole on the grid and sliced into chunks."""
    common = ["fit", *map(str, bags), "--step-period", "1", *SMALL, "--preset", "guide"]
    code, _, stderr = run_entry([*common, "-o", str(tmp_path / "mem.npz")], capsys)
    assert code == 0, stderr
    code, _, stderr = run_entry(
        [*common, "-o", str(tmp_path / "str.npz"), "--stream", "--chunk-steps", "100"], capsys
    )
    assert code == 0, stderr
    assert "preset guide with its robot-bag settings" in stderr
    streamed = load_model(tmp_path / "str.npz")
    assert streamed.config.normalize_ht_features  # the robot-bag default, streamed too
    assert_same(streamed, load_model(tmp_path / "mem.npz"))
    recorded = [read_metadata(tmp_path / f"{name}.npz")["training"]["bags"][0]["topics"]
                for name in ("str", "mem")]
    assert recorded[0]["pose_frame"] == recorded[1]["pose_frame"]  # plot and policy read it


@pytest.fixture
def silent_listener():
    """A TCP port that accepts connections and never says a word."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(5)
        yield sock.getsockname()[1]


@pytest.mark.slow
@pytest.mark.timeout(60)  # a scheduler timeout that is not honoured hangs: the test fails
def test_a_scheduler_that_accepts_but_never_answers_is_one_line_in_time(
    bags, tmp_path, capsys, silent_listener
):
    pytest.importorskip("distributed")
    out = tmp_path / "m.npz"
    argv = ["fit", str(bags[0]), "-o", str(out), "--scheduler", f"tcp://127.0.0.1:{silent_listener}"]
    code, _, stderr = run_entry([*argv, "--scheduler-timeout", "0.5", *SMALL], capsys)
    assert code == 1
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("learner: error: no Dask scheduler answers at")
    assert f"127.0.0.1:{silent_listener}" in last and "within 0.5 s" in last
    assert "Traceback" not in stderr and not out.exists()


def test_a_real_scheduler_passes_the_probe_and_lost_tasks_are_one_line():
    distributed = pytest.importorskip("distributed")
    from learner.distributed import dask_client

    with distributed.LocalCluster(
        n_workers=0, processes=False, dashboard_address=None, scheduler_kwargs=SCHEDULER_HTTP
    ) as cluster:
        address = cluster.scheduler_address
        with dask_client(scheduler=address, timeout=5) as client:
            assert client.scheduler.address == address
        killed = distributed.KilledWorker("fit-1", types.SimpleNamespace(address="tcp://w:1"), 3)
        lost = [killed, distributed.client.FutureCancelledError("fit-2", reason="scheduler gone")]
        for error in lost:
            with pytest.raises(ConfigError) as caught, dask_client(scheduler=address):
                raise error
            message = str(caught.value)
            assert message.startswith("the Dask cluster lost a task") and "\n" not in message
        assert "'fit-1' on 4 different workers" in message or "fit-2" in message


def test_a_cluster_with_no_workers_left_is_a_one_line_error_not_a_hang():
    """Dask would wait for new workers forever (e.g. every remote worker disconnected)."""
    distributed = pytest.importorskip("distributed")
    from learner.distributed import gather

    with (
        distributed.LocalCluster(
            n_workers=0, processes=False, dashboard_address=None, scheduler_kwargs=SCHEDULER_HTTP
        ) as cluster,
        distributed.Client(cluster, set_as_default=False) as client,
    ):
        future = client.submit(sum, [3, 4], pure=False)  # no worker will ever run it
        with pytest.raises(ConfigError, match="has no workers left") as caught:
            gather(client, [future], poll=0.5)
        assert "\n" not in str(caught.value)


@pytest.mark.slow
def test_workers_option_writes_the_streamed_model(bags, tmp_path, capfd):
    pytest.importorskip("distributed")
    common = ["fit", *map(str, bags), *SMALL]
    code, _, stderr = run_entry([*common, "-o", str(tmp_path / "s.npz"), "--stream"], capfd)
    assert code == 0, stderr
    argv = [*common, "-o", str(tmp_path / "d.npz"), "--workers", "1"]
    # another cluster's HTTP server on Dask's default port (8787) is no concern of the fit's
    with socket.socket() as other, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with contextlib.suppress(OSError):  # taken already: as good
            other.bind(("127.0.0.1", 8787))
            other.listen()
        code, stdout, stderr = run_entry(argv, capfd)
    assert code == 0, stderr
    assert not [w for w in caught if "already in use" in str(w.message)]
    assert "connecting to a local cluster of 1 worker(s)" in stderr
    assert "1200 steps, 2 segment(s), 399 episodes" in stdout
    model = load_model(tmp_path / "d.npz")
    assert model.fit_info["streamed"]["engine"].startswith("dask, 1 worker(s)")
    assert_same(model, load_model(tmp_path / "s.npz"))


@pytest.mark.slow
def test_a_bag_that_vanishes_under_dask_is_one_line_without_worker_tracebacks(
    bags, tmp_path, capfd, monkeypatch
):
    pytest.importorskip("distributed")
    import learner.fit

    doomed = tmp_path / "doomed"
    shutil.copytree(bags[1], doomed)
    visible = learner.fit.check_bags_visible

    def check_then_delete(client, paths):  # the bag goes after the check, before pass 1
        visible(client, paths)
        shutil.rmtree(doomed)

    monkeypatch.setattr(learner.fit, "check_bags_visible", check_then_delete)
    out = tmp_path / "m.npz"
    argv = ["fit", str(bags[0]), str(doomed), "-o", str(out), "--workers", "1", *SMALL]
    code, _, stderr = run_entry(argv, capfd)
    assert code == 1 and not out.exists()
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("learner: error:") and str(doomed) in last
    assert "Traceback" not in stderr and "Compute Failed" not in stderr


def test_a_refinement_on_dask_refuses_bags_this_process_cannot_read(bags, tmp_path):
    """The refinement reads its steps in the client: bags only the workers see are refused
    before the cluster's passes, with the way out."""
    from learner.distributed import check_bags_readable_here

    why = "the refinement reads its steps here: mount them here, or add --refine-epochs 0"
    check_bags_readable_here(bags, why)  # visible here: nothing to say
    with pytest.raises(ConfigError, match="--refine-epochs 0") as caught:
        check_bags_readable_here([*bags, tmp_path / "on-the-workers-only"], why)
    assert "on-the-workers-only" in str(caught.value)
