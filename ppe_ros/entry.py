"""Console-script entry points (``extractor``, ``process_bag``): the command's module is imported inside the
entry point, so that a Ctrl-C while it loads (rclpy, numpy, numba and rosbags take about half a second)
ends with one line and exit code 130, as a Ctrl-C later does, instead of a traceback through the imports.
Only this module and the (lazy) package are imported before that.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable


def load_main(module: str, command: str) -> Callable[[], int] | None:
    """``module.main``, or None (after one line on stderr) when a Ctrl-C interrupted its import."""
    try:
        return importlib.import_module(module).main
    except KeyboardInterrupt:
        print(f'{command}: interrupted', file=sys.stderr)
        return None


def extractor() -> int:
    """``ros2 run ppe_ros extractor``: :func:`ppe_ros.ros.node.main`."""
    main = load_main('ppe_ros.ros.node', 'extractor')
    return 130 if main is None else main()


def process_bag() -> int:
    """``ros2 run ppe_ros process_bag``: :func:`ppe_ros.ros.bag.main`."""
    main = load_main('ppe_ros.ros.bag', 'process_bag')
    return 130 if main is None else main()
