"""``python -m tpsr_ros.filter_node``: run the filter node."""

from tpsr_ros.filter_node.node import main

if __name__ == "__main__":
    main()
