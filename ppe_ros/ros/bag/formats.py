"""File signatures of the storage formats ``process_bag`` reads."""

from __future__ import annotations

MCAP_MAGIC = b'\x89MCAP0\r\n'
SQLITE_MAGIC = b'SQLite format 3\x00'
ROS1_MAGIC = b'#ROSBAG V'
ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'
