"""``python -m tpsr_ros.view.layouts``: write or check the shipped layouts."""

from tpsr_ros.cli import run_cli
from tpsr_ros.view.layouts import PROG, main

if __name__ == "__main__":
    run_cli(PROG, main)
