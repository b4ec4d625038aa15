"""``python -m ppe_ros.ros.bag IN OUT``: the same as ``process_bag IN OUT``."""

import sys

from ppe_ros.ros.bag.cli import main

sys.exit(main())
