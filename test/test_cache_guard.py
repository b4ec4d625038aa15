"""The numba cache guard of ppe_ros.core.ppe: a changed callee in another module clears the package's cache.

numba's cache=True keys a kernel on its own file: without the guard, a kernel of core/ppe that inlines
fitting.solve_sym3 keeps its stale machine code after solve_sym3 changes (shown below with the guard
switched off, so the end-to-end test can fail).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ppe_ros.core.ppe import cache_guard
from ppe_ros.core.ppe.cache_guard import (
    STAMP_NAME,
    clear_stale_cache,
    guard_module_cache,
    kernel_sources,
    sources_digest,
)

PACKAGE = Path(__file__).resolve().parents[1] / 'ppe_ros'


def _touch(directory: Path, *names: str) -> None:
    for name in names:
        (directory / name).write_bytes(b'x')


def test_a_stamp_mismatch_clears_the_package_cache_files_only(tmp_path):
    _touch(tmp_path, 'greedy._ppe_kernel-300.py311.nbi', 'greedy._ppe_kernel-300.py311.1.nbc', 'state._fit-9.py311.nbi')
    _touch(tmp_path, 'fitting.fit_rays-216.py311.nbi', 'greedy.py.txt', 'greedyish._k-1.py311.nbi')
    assert clear_stale_cache(tmp_path, ['greedy', 'state'], 'abc') is True
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([STAMP_NAME, 'fitting.fit_rays-216.py311.nbi', 'greedy.py.txt', 'greedyish._k-1.py311.nbi'])
    assert (tmp_path / STAMP_NAME).read_text().strip() == 'abc'
    # the same digest again: nothing is cleared
    _touch(tmp_path, 'greedy._ppe_kernel-300.py311.nbi')
    assert clear_stale_cache(tmp_path, ['greedy', 'state'], 'abc') is False
    assert (tmp_path / 'greedy._ppe_kernel-300.py311.nbi').exists()
    # another digest: cleared again
    assert clear_stale_cache(tmp_path, ['greedy', 'state'], 'def') is True
    assert not (tmp_path / 'greedy._ppe_kernel-300.py311.nbi').exists()


def test_a_module_outside_the_package_is_guarded_on_the_module_it_inlines_from(tmp_path, monkeypatch):
    """ppe_ros.core.boundary_join's kernels inline consolidation.py's helpers: a change there clears them."""
    monkeypatch.setenv('PPE_NUMBA_CACHE_GUARD', '1')
    sources, cache = tmp_path / 'src', tmp_path / 'cache'
    sources.mkdir()
    cache.mkdir()
    module, dependency = sources / 'boundary_join.py', sources / 'consolidation.py'
    module.write_text('# kernels\n')
    dependency.write_text('# helpers\n')
    _touch(cache, 'boundary_join._cost-10.py311.nbi', 'consolidation._find-3.py311.nbi')
    assert guard_module_cache(module, [dependency], cache) is True  # no stamp yet
    assert sorted(p.name for p in cache.iterdir()) == [f'boundary_join.{STAMP_NAME}', 'consolidation._find-3.py311.nbi']
    _touch(cache, 'boundary_join._cost-10.py311.nbi')
    assert guard_module_cache(module, [dependency], cache) is False  # unchanged: kept
    assert (cache / 'boundary_join._cost-10.py311.nbi').exists()
    dependency.write_text('# helpers, changed\n')
    assert guard_module_cache(module, [dependency], cache) is True
    assert not (cache / 'boundary_join._cost-10.py311.nbi').exists()
    assert (cache / 'consolidation._find-3.py311.nbi').exists()  # numba keys that one on its own file
    monkeypatch.setenv('PPE_NUMBA_CACHE_GUARD', '0')
    dependency.write_text('# changed again\n')
    _touch(cache, 'boundary_join._cost-10.py311.nbi')
    assert guard_module_cache(module, [dependency], cache) is False


def test_a_file_that_vanishes_meanwhile_is_skipped(tmp_path, monkeypatch):
    """Two processes importing at once: the other one deleted a file between the listing and the unlink."""
    _touch(tmp_path, 'queue._q_push-10.py311.nbi', 'queue._q_push-10.py311.1.nbc')
    real_unlink = os.unlink

    def racing_unlink(path, *args, **kwargs):
        real_unlink(path)  # the other process was first
        raise FileNotFoundError(path)

    monkeypatch.setattr(cache_guard.os, 'unlink', racing_unlink)
    assert clear_stale_cache(tmp_path, ['queue'], 'abc') is True
    assert sorted(p.name for p in tmp_path.iterdir()) == [STAMP_NAME]


def test_the_digest_covers_the_package_and_fitting(tmp_path):
    sources = kernel_sources()
    names = {p.name for p in sources}
    assert {'greedy.py', 'queue.py', 'state.py', 'seeds.py', 'fitting.py'} <= names
    copy = tmp_path / 'fitting.py'
    shutil.copy(PACKAGE / 'core' / 'fitting.py', copy)
    package = sorted((PACKAGE / 'core' / 'ppe').glob('*.py'))
    before = sources_digest([*package, copy])
    copy.write_text(copy.read_text() + '\n# changed\n')
    assert sources_digest([*package, copy]) != before


def _run(root: Path, cache: Path, guard: bool, code: str) -> str:
    env = {**os.environ, 'PYTHONPATH': str(root), 'NUMBA_CACHE_DIR': str(cache)}
    env['PPE_NUMBA_CACHE_GUARD'] = '1' if guard else '0'
    done = subprocess.run([sys.executable, '-c', code], cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


#: A kernel of core/ppe (state._model_merge) that inlines fitting.solve_sym3, compiled into the cache.
_MODEL_MERGE = """
import numpy as np
from ppe_ros.core.ppe import state
from ppe_ros.core.ppe.layout import _NPF, _PH, _PW
pf = np.zeros((2, _NPF))
pf[:, _PH:_PH + 6] = (2.0, 0.1, 0.0, 1.5, 0.2, 1.0)
pf[0, _PW:_PW + 3] = (0.1, 0.2, 0.3)
pf[1, _PW:_PW + 3] = (0.3, 0.1, 0.2)
print(repr(state._model_merge(pf, 0, 1)[0]))
print(state.__file__)
"""


def test_a_changed_callee_in_another_module_is_not_served_stale(tmp_path):
    """A temporary copy of the package with its own NUMBA_CACHE_DIR: change fitting.solve_sym3 (which
    state._model_merge inlines) after the kernel was cached. With the guard off numba loads the stale
    kernel (the old value); with it on the cache is cleared and the kernel compiled from the new source."""
    root = tmp_path / 'tree'
    shutil.copytree(PACKAGE, root / 'ppe_ros', ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
    cache = tmp_path / 'cache'
    first, where = _run(root, cache, True, _MODEL_MERGE).splitlines()
    assert where.startswith(str(root))
    assert any(cache.rglob('state._model_merge-*.nbi')) and any(cache.rglob(STAMP_NAME))
    fitting = root / 'ppe_ros' / 'core' / 'fitting.py'
    source = fitting.read_text()
    assert source.count('    inv = 1.0 / det if ok else 0.0\n') == 1
    fitting.write_text(source.replace('    inv = 1.0 / det if ok else 0.0\n', '    inv = 2.0 / det if ok else 0.0\n'))
    stale = _run(root, cache, False, _MODEL_MERGE).splitlines()[0]
    assert stale == first  # numba alone serves the cached kernel of the old solve_sym3
    fresh = _run(root, cache, True, _MODEL_MERGE).splitlines()[0]
    assert float(fresh) == pytest.approx(2 * float(first), rel=1e-12)
    # and the next import with the guard keeps the fresh cache (the stamp now matches)
    assert _run(root, cache, True, _MODEL_MERGE).splitlines()[0] == fresh


def test_a_changed_layout_constant_is_not_served_stale(tmp_path):
    """layout.py defines no kernel, but its constants (here the column of w in the plane rows) are
    compiled into the kernels that read them: moving w must recompile state._model_merge, which reads it."""
    root = tmp_path / 'tree'
    shutil.copytree(PACKAGE, root / 'ppe_ros', ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
    cache = tmp_path / 'cache'
    first = _run(root, cache, True, _MODEL_MERGE).splitlines()[0]
    assert float(first) > 0.0
    layout = root / 'ppe_ros' / 'core' / 'ppe' / 'layout.py'
    source = layout.read_text()
    assert source.count('\n_PW = 1  #') == 1
    layout.write_text(source.replace('\n_PW = 1  #', '\n_PW = 13  #'))  # the script writes w there now
    stale = _run(root, cache, False, _MODEL_MERGE).splitlines()[0]
    assert float(stale) == 0.0  # numba alone: the cached kernel reads w at the old column (zeros now)
    assert _run(root, cache, True, _MODEL_MERGE).splitlines()[0] == first
