"""Files of tpsr-ros, no middleware: ROS messages, rosbag2/MCAP bags, trajectories read
from bags, pickle-free ``.npz`` archives, model and policy files and their checks.

Imports :mod:`tpsr_ros.core`, rosbags and mcap; never rclpy, cyclonedds or sim_node.
"""
