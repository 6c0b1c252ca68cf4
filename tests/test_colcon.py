"""The repository is a colcon (ament_python) package: package.xml, setup.py/setup.cfg, marker.

A real ``colcon build`` of a workspace holding a copy of the repository (its tracked
files, as a clone has them) into a temporary directory: the node executables land in
``install/lib/tpsr_ros/`` where ``ros2 run tpsr_ros <node>`` looks, and run from the
installed copy. colcon comes from the test extra (colcon-common-extensions, catkin_pkg).
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NODES = ("sim_node", "filter_node", "learner_node", "record", "play", "view")


def _colcon() -> str | None:
    here = Path(sys.executable).parent / "colcon"
    return str(here) if here.exists() else shutil.which("colcon")


def test_package_xml_is_format_3_ament_python_with_the_project_version():
    catkin_pkg = pytest.importorskip("catkin_pkg.package", reason="catkin_pkg not installed")
    package = catkin_pkg.parse_package(ROOT / "package.xml")
    package.validate()
    assert package.package_format == 3 and package.name == "tpsr_ros"
    assert package.get_build_type() == "ament_python"
    assert package.version == version("tpsr-ros")
    assert {"rclpy", "sensor_msgs", "geometry_msgs", "rosgraph_msgs", "diagnostic_msgs"} <= {
        d.name for d in package.exec_depends
    }
    assert (ROOT / "resource" / "tpsr_ros").is_file()


def _copy_tracked_files(dest: Path) -> None:
    """What a clone holds: tracked (and new, not ignored) files; no .venv, no build output."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT, capture_output=True, check=True,
    ).stdout.split(b"\0")
    for name in filter(None, (n.decode() for n in listed)):
        source = ROOT / name
        if source.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)


def _build(tmp_path: Path, *options: str) -> tuple[Path, dict[str, str]]:
    """A colcon workspace holding a copy of the repository, built with ``options``; its
    path and the environment the build ran in."""
    colcon = _colcon()
    if colcon is None:
        pytest.skip("colcon is not installed (pip install colcon-common-extensions)")
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs the git checkout to copy the repository's files")
    workspace = tmp_path / "ws"
    _copy_tracked_files(workspace / "src" / "tpsr-ros")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    build = subprocess.run(
        [colcon, "build", *options, "--merge-install", "--event-handlers", "console_direct-"],
        cwd=workspace, capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    assert "1 package finished" in build.stdout + build.stderr
    return workspace, env


@pytest.mark.slow
def test_colcon_build_installs_runnable_node_executables(tmp_path):
    workspace, env = _build(tmp_path)

    install = workspace / "install"
    for node in NODES:
        exe = install / "lib" / "tpsr_ros" / node
        assert exe.is_file() and os.access(exe, os.X_OK), node
    marker = install / "share" / "ament_index" / "resource_index" / "packages" / "tpsr_ros"
    assert marker.is_file()
    assert (install / "share" / "tpsr_ros" / "package.xml").is_file()
    launch = install / "share" / "tpsr_ros" / "launch" / "closed_loop.launch.xml"
    assert launch.read_bytes() == (ROOT / "launch" / "closed_loop.launch.xml").read_bytes()
    layouts = ROOT / "tpsr_ros" / "view" / "layouts"
    shipped = sorted(p.name for p in layouts.glob("tpsr_view.*"))
    installed = install / "share" / "tpsr_ros" / "layouts"
    assert shipped and sorted(p.name for p in installed.iterdir()) == shipped
    for name in shipped:
        assert (installed / name).read_bytes() == (layouts / name).read_bytes()
    (site,) = install.glob("lib/python3*/site-packages")
    assert {"tpsr_ros", "sim_node", "learner"} <= {p.name for p in site.iterdir()}

    # what `source install/setup.bash` sets for Python packages and the ament index
    run_env = {
        **env,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])),
        "AMENT_PREFIX_PATH": str(install),
        "TPSR_TRANSPORT": "inproc",
    }
    # ros2 run's lookup: the package prefix from the ament index, then lib/<package>/<exe>
    lookup = subprocess.run(
        [sys.executable, "-c",
         "from ament_index_python.packages import get_package_prefix as p; "
         "print(p('tpsr_ros'))"],
        capture_output=True, text=True, env=run_env, timeout=60, cwd=tmp_path,
    )
    if importlib.util.find_spec("ament_index_python") is not None:  # the ros extra has it
        assert lookup.returncode == 0, lookup.stderr
        assert lookup.stdout.strip() == str(install)
    where = subprocess.run(
        [sys.executable, "-c", "import tpsr_ros, sim_node; print(tpsr_ros.__file__)"],
        capture_output=True, text=True, env=run_env, timeout=60, cwd=tmp_path,
    )
    assert where.stdout.startswith(str(site)), where  # the installed copy, not the checkout
    for node, needle in (("filter_node", "model"), ("sim_node", "environment"),
                         ("record", "--output"), ("play", "--rate"), ("view", "--port")):
        result = subprocess.run(
            [str(install / "lib" / "tpsr_ros" / node), "--help"],
            capture_output=True, text=True, env=run_env, timeout=120, cwd=tmp_path,
        )
        assert result.returncode == 0, (node, result.stderr)
        assert needle in result.stdout, (node, result.stdout)


@pytest.mark.slow
def test_a_symlink_install_builds_and_its_nodes_name_themselves_as_ros2_run(tmp_path):
    """``colcon build --symlink-install`` (what most workspaces use) links setup.py and
    setup.cfg into the build directory without pyproject.toml; the build must still name
    its packages, and the executables run the checkout's code."""
    workspace, env = _build(tmp_path, "--symlink-install")
    # what `source install/setup.bash` sets: a develop install's build directory (colcon's
    # pythonpath_develop hook) and site-packages on PYTHONPATH
    (site,) = (workspace / "install").glob("lib/python3*/site-packages")
    path = [str(workspace / "build" / "tpsr_ros"), str(site)]
    run_env = {**env, "TPSR_TRANSPORT": "inproc", "PYTHONPATH": os.pathsep.join(path)}
    exe = workspace / "install" / "lib" / "tpsr_ros" / "sim_node"
    result = subprocess.run(
        [str(exe), "--help"], capture_output=True, text=True, env=run_env, timeout=120,
        cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage: ros2 run tpsr_ros sim_node"), result.stdout
    bad = subprocess.run(
        [str(exe), "--ros-args", "-p", "rate:=-1"], capture_output=True, text=True,
        env=run_env, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert bad.returncode == 2 and bad.stderr.startswith("ros2 run tpsr_ros sim_node: error:")
