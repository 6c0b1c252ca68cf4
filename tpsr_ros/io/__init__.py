"""Files and wire formats of tpsr-ros, no middleware.

ROS messages (:mod:`~tpsr_ros.io.messages`), QoS profiles and their bag form
(:mod:`~tpsr_ros.io.qos`), rosbag2/MCAP bags (:mod:`~tpsr_ros.io.bag`), trajectories read
from bags (:mod:`~tpsr_ros.io.trajectory`), pickle-free ``.npz`` archives, model and policy
files (:mod:`~tpsr_ros.io.model_io`, :mod:`~tpsr_ros.io.policy`) and the check that a model
and a policy can run together in a filter node (:mod:`~tpsr_ros.io.filter_inputs`).

Imports :mod:`tpsr_ros.core`, rosbags and mcap; never rclpy, cyclonedds or sim_node.
"""
