"""Readers of damaged storage files, as far as they go: the one place that uses rosbags internals.

:class:`SalvageMcapReader` subclasses rosbags' MCAP storage reader (its ``_open``, ``bio``,
``meta_scan``, ``statistics``) and is put in a rosbag2 reader as its ``storage``;
:class:`SalvageRos1Reader` uses the record helpers of ``rosbags.rosbag1.reader`` (``Header``,
``RecordType``, ``read_bytes``, ``read_uint32``, ``decompressors``, ``normalize``);
:class:`SalvageSqliteReader` reads SQLite pages itself. They are written against rosbags
:data:`ROSBAGS_VERSION`, which a test pins to requirements.txt: upgrading rosbags means running
test_bag.py and test_fuzz_bags.py and then changing :data:`ROSBAGS_VERSION` here.
"""

from __future__ import annotations

from ppe_ros.ros.bag.salvage.mcap import SalvageMcapReader, counts_exact, salvage_scan_error, salvaged_mcap_reader
from ppe_ros.ros.bag.salvage.ros1 import SalvagedConnection, SalvageRos1Reader
from ppe_ros.ros.bag.salvage.sqlite import SalvageSqliteReader

#: The rosbags version these readers are written against (pinned in requirements.txt).
ROSBAGS_VERSION = '0.11.9'

__all__ = [
    'ROSBAGS_VERSION',
    'SalvageMcapReader',
    'SalvageRos1Reader',
    'SalvageSqliteReader',
    'SalvagedConnection',
    'counts_exact',
    'salvage_scan_error',
    'salvaged_mcap_reader',
]
