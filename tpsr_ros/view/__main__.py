"""``python -m tpsr_ros.view``: serve the view topics to Foxglove."""

from tpsr_ros.view.node import main

if __name__ == "__main__":
    main()
