"""Shared pytest fixtures: the path to ../shared/data and ROS isolation settings."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get('PPE_SHARED_DATA', REPO_ROOT.parent / 'shared' / 'data'))


@pytest.fixture(scope='session')
def shared_data() -> Path:
    """``../shared/data``; tests that need it skip on a fresh clone, where it does not exist."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f'needs the shared data sets at {SHARED_DATA} (present in CI, absent in a fresh clone)')
    return SHARED_DATA


@pytest.fixture
def child_hook_env(tmp_path):
    """A function: write ``source`` as ``sitecustomize.py`` into tmp_path and return ``{'PYTHONPATH': ...}`` that
    puts it first for a child process, which runs it at start-up (a test-only hook; nothing in ppe_ros)."""

    def make(source: str) -> dict[str, str]:
        (tmp_path / 'sitecustomize.py').write_text(source)
        return {'PYTHONPATH': os.pathsep.join([str(tmp_path), os.environ.get('PYTHONPATH', '')])}

    return make
