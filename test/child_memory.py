"""Peak resident memory of a command run by a test, without the test process's own memory in it.

On Linux a child's ``ru_maxrss`` (``os.wait4``, ``RUSAGE_CHILDREN``) includes the resident size of the
process it was started from: subprocess starts children with vfork, and exec records the high-water mark
of the memory it replaces, here the parent's. A child of a pytest process that has grown to 1 GB reports
1 GB whatever it uses itself. So the command runs as a grandchild of a small launcher (this file run as a
script), whose memory is what the grandchild's exec replaces; the launcher writes the grandchild's
``ru_maxrss`` (KiB) into a report file and exits with its exit code.

    command = measured([sys.executable, '-m', 'ppe_ros.cli', 'info', path], report)   # then run it
    peak_kib(report)
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

LAUNCHER = Path(__file__).resolve()


def measured(command: list[str], report: Path) -> list[str]:
    """``command`` run through the launcher, which writes its peak resident memory (KiB) into ``report``."""
    return [sys.executable, str(LAUNCHER), str(report), *command]


def peak_kib(report: Path) -> int:
    """The peak resident memory (KiB) that the launcher wrote into ``report``."""
    return int(Path(report).read_text())


def _launch(report: str, command: list[str]) -> int:
    process = subprocess.Popen(command)
    _, status, usage = os.wait4(process.pid, 0)
    Path(report).write_text(str(usage.ru_maxrss))
    code = os.waitstatus_to_exitcode(status)
    return code if code >= 0 else 128 - code  # killed by signal N: 128 + N, as a shell reports it


if __name__ == '__main__':
    sys.exit(_launch(sys.argv[1], sys.argv[2:]))
