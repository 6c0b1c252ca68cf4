"""The ROS-free core of tpsr-ros: numpy and scipy only.

Whitening (Algorithm 1), features (Algorithm 2), the TPSR fit (Algorithm 3) and filter
(Algorithm 4), the PCA baseline, fitted Q-iteration, the state-model interface, the online
tracker, episode cutting and the 25-action table. Nothing here imports rosbags, mcap,
rclpy, cyclonedds or sim_node (``tests/test_layers.py`` checks it).
"""
