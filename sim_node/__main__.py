"""``python -m sim_node --ros-args -p environment:=full -p mode:=explore -p rate:=10``.

Runs the simulator node until SIGINT/SIGTERM; ``--help`` lists its parameters.
"""

from sim_node.node import SimNode
from tpsr_ros.runtime import run_node

if __name__ == "__main__":
    run_node(SimNode, prog="python -m sim_node")
