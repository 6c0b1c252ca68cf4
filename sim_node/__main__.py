"""``python -m sim_node --ros-args -p environment:=full -p mode:=explore -p rate:=10``.

Runs the simulator node until SIGINT/SIGTERM; ``--help`` lists its parameters.
"""

from sim_node.node import SimNode
from tpsr_ros.runtime import run_node


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``python -m sim_node`` (and of colcon's ``lib/tpsr_ros/sim_node``)."""
    run_node(SimNode, prog="python -m sim_node", argv=argv)


if __name__ == "__main__":
    main()
