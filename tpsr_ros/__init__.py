"""tpsr-ros: transformed predictive state representations for ROS 2 robots.

The ROS-free core (whitening, features, TPSR fit and filter, PCA baseline, fitted Q,
model files, bag I/O) lives here beside the thin node runtime; the core never imports
rclpy, cyclonedds or the transport.
"""

__version__ = "0.1.0"
