"""setup.py for colcon's ament_python build; pip uses pyproject.toml (same metadata).

colcon (which sets ``COLCON=1``) gets what an ament_python package installs besides the
Python packages: the ament resource marker, package.xml, and the node executables
``lib/tpsr_ros/{sim_node,filter_node,learner_node,record,play,view}`` (setup.cfg puts scripts there),
which ``ros2 run tpsr_ros <node>`` starts, ``share/tpsr_ros/launch/*.launch.xml`` for
``ros2 launch tpsr_ros <file>``, and the viewers' layouts in ``share/tpsr_ros/layouts/``;
also under ``colcon build --symlink-install``, which runs this file without
pyproject.toml. pip installs get no console scripts: the nodes run
with ``python -m``, and names like ``record`` and ``play`` do not belong in a venv's bin/.
"""

import os
import re
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.dist import Distribution

PACKAGE = "tpsr_ros"
NODES = {
    "sim_node": "sim_node.__main__:main",
    "filter_node": "tpsr_ros.filter_node:main",
    "learner_node": "tpsr_ros.learner_node:main",
    "record": "tpsr_ros.record:main",
    "play": "tpsr_ros.play:main",
    "view": "tpsr_ros.view:main",
}
LAYOUTS = "tpsr_ros/view/layouts"


class _ColconDistribution(Distribution):
    """Requires-Python as text, as colcon reads it.

    colcon-python-setup-py evaluates the repr of the configured distribution with
    ``ast.literal_eval``; pyproject.toml's ``requires-python`` becomes a ``SpecifierSet``
    there, whose repr is no literal (colcon/colcon-python-setup-py issues 33 and 56).
    """

    def parse_config_files(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        super().parse_config_files(*args, **kwargs)
        for holder in (self, self.metadata):
            if getattr(holder, "python_requires", None) is not None:
                holder.python_requires = str(holder.python_requires)


extra = {}
if os.environ.get("COLCON") == "1":
    extra = {
        "distclass": _ColconDistribution,
        "data_files": [
            ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
            (f"share/{PACKAGE}", ["package.xml"]),
            (f"share/{PACKAGE}/launch", sorted(str(f) for f in Path("launch").glob("*.xml"))),
            (f"share/{PACKAGE}/layouts", sorted(str(f) for f in Path(LAYOUTS).glob("tpsr_view.*"))),
        ],
        "entry_points": {"console_scripts": [f"{k} = {v}" for k, v in NODES.items()]},
    }

if os.environ.get("COLCON") == "1" and not Path("pyproject.toml").exists():
    # colcon build --symlink-install runs this file from a build directory of links to
    # setup.py, setup.cfg and the packages, without pyproject.toml: take the name and
    # version from the source's pyproject.toml and name the packages (no auto-discovery
    # of the build directory's launch/, resource/ and prefix_override/).
    source = (Path(__file__).resolve().parent / "pyproject.toml").read_text(encoding="utf-8")
    fields = dict(re.findall(r'^(name|version) = "([^"]+)"$', source, re.MULTILINE))
    extra.update(
        name=fields["name"],
        version=fields["version"],
        packages=find_packages(include=["tpsr_ros*", "sim_node*", "learner*"]),
    )

setup(**extra)
