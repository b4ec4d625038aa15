"""The launcher of test/child_memory.py reports a command's own peak memory, not its parent's."""

from __future__ import annotations

import subprocess
import sys

from child_memory import LAUNCHER, measured, peak_kib

#: Resident memory (MB) that the parent of the launcher holds, and that a command allocates.
PARENT_MB = 600
COMMAND_MB = 300


def _run_from_a_large_parent(command: list[str], report) -> int:
    """Run ``measured(command, report)`` from a Python process that holds PARENT_MB resident; its exit code."""
    parent = (
        'import subprocess, sys\n'
        f'held = bytearray({PARENT_MB} << 20)\n'
        'held[::4096] = b"x" * len(held[::4096])\n'  # touch every page: resident
        f'sys.exit(subprocess.run({measured(command, report)!r}).returncode)\n'
    )
    return subprocess.run([sys.executable, '-c', parent], timeout=120).returncode


def test_a_small_command_started_from_a_large_parent_reports_its_own_memory(tmp_path):
    report = tmp_path / 'peak.txt'
    assert _run_from_a_large_parent([sys.executable, '-c', 'pass'], report) == 0
    assert 1 << 10 < peak_kib(report) < 100 << 10  # an interpreter: tens of MB, not the parent's 600


def test_a_command_that_allocates_reports_it_and_its_exit_code_comes_back(tmp_path):
    report = tmp_path / 'peak.txt'
    allocate = f'held = bytearray({COMMAND_MB} << 20); held[::4096] = b"x" * len(held[::4096]); raise SystemExit(3)'
    assert _run_from_a_large_parent([sys.executable, '-c', allocate], report) == 3
    assert COMMAND_MB << 10 < peak_kib(report) < (COMMAND_MB + 100) << 10


def test_a_command_killed_by_a_signal_exits_with_128_plus_the_signal(tmp_path):
    report = tmp_path / 'peak.txt'
    kill_self = 'import os, signal; os.kill(os.getpid(), signal.SIGTERM)'
    result = subprocess.run([sys.executable, str(LAUNCHER), str(report), sys.executable, '-c', kill_self], timeout=60)
    assert result.returncode == 128 + 15
    assert peak_kib(report) > 0
