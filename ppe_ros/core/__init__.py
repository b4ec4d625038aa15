"""Pure core of ppe_ros: scan model, plane fitting, PPE extraction, synthetic scans, evaluation.

Only numpy and numba are needed here; nothing in ``ppe_ros.core`` imports ROS.
"""
