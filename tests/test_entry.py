"""Help and errors name the program as the user started it."""

from __future__ import annotations

from tpsr_ros.runtime.entry import program_name


def test_the_program_is_named_as_started() -> None:
    default = "python -m sim_node"
    assert program_name(default, "/repo/sim_node/__main__.py") == default
    assert program_name(default, "") == default
    ros2_run = "/ws/install/lib/tpsr_ros/sim_node"
    assert program_name(default, ros2_run) == "ros2 run tpsr_ros sim_node"
    assert program_name(default, "/usr/local/bin/filter_node") == "filter_node"
