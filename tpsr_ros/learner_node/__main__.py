"""``python -m tpsr_ros.learner_node``: run the learner node."""

from tpsr_ros.learner_node.node import main

if __name__ == "__main__":
    main()
