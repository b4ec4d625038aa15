"""Numba cache guard: drop the package's cached kernels when a module their kernels call has changed.

numba's ``cache=True`` keys a cached kernel on its own source file only: when a function it calls
(or inlines) in another module changes, the stale machine code is loaded anyway. The kernels of
``ppe_ros.core.ppe`` call across its modules and into ``ppe_ros.core.fitting``, and numba compiles the
global constants they read (layout.py's row layouts and fit tolerances) into them. So at import of the
package (before any kernel is compiled or loaded) :func:`guard_kernel_cache` hashes the sources of all
its modules and fitting.py; when the hash differs from the stamp kept in the package's numba cache
directory (``NUMBA_CACHE_DIR`` when set, else numba's own choice: ``__pycache__`` next to the sources or
the user-wide cache), the package's cache files (``*.nbi``, ``*.nbc``) are deleted and the new stamp is
written. Cost: hashing about 150 KB of source per import (well under a millisecond).

Two processes importing at once may both clear and both write the stamp (the same content, written
through a temporary file and an atomic rename); a file that vanishes meanwhile is skipped.
Set ``PPE_NUMBA_CACHE_GUARD=0`` to switch the guard off (the tests use it to show the stale cache).
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

#: The stamp file in the package's cache directory.
STAMP_NAME = 'ppe-kernel-sources.sha256'
PACKAGE_DIR = Path(__file__).resolve().parent
#: Sources outside the package that its kernels call (their own caches are keyed on themselves).
DEPENDENCIES = (PACKAGE_DIR.parent / 'fitting.py',)


def kernel_modules(package_dir: Path = PACKAGE_DIR) -> list[Path]:
    """The package's modules that define numba kernels or intrinsics (the others' changes need no recompile)."""
    return [p for p in sorted(package_dir.glob('*.py')) if 'nb.njit' in (text := p.read_text()) or '@intrinsic' in text]


def kernel_sources(package_dir: Path = PACKAGE_DIR, dependencies=DEPENDENCIES) -> list[Path]:
    """Every module of the package and the dependencies, in a fixed order.

    Every module, not only the kernel modules: numba compiles the global constants a kernel reads
    (the row layouts and fit tolerances of layout.py) into its machine code, so a changed constant
    needs a recompile as much as a changed callee does.
    """
    return sorted(package_dir.glob('*.py')) + [Path(d) for d in dependencies]


def sources_digest(paths: list[Path]) -> str:
    """SHA-256 (hex) over the names and contents of the source files."""
    digest = hashlib.sha256()
    for path in paths:
        digest.update(path.name.encode() + b'\0')
        digest.update(path.read_bytes())
        digest.update(b'\0')
    return digest.hexdigest()


def _probe():
    """A function of this package's directory: numba's cache locators place its kernels' files by it."""


def cache_directory(probe=_probe) -> Path | None:
    """The directory numba caches the kernels of ``probe``'s directory in (default: this package's; None:
    numba could not cache them).

    Asks numba's own locator (as a kernel of that directory would), so NUMBA_CACHE_DIR,
    NUMBA_CACHE_LOCATOR_CLASSES and the fallbacks (a read-only tree: the user-wide cache) are honoured.
    """
    from numba.core.caching import CompileResultCacheImpl

    try:
        return Path(CompileResultCacheImpl(probe).locator.get_cache_path())
    except RuntimeError:  # no locator available
        return None


def clear_stale_cache(cache_dir: Path, module_stems: list[str], digest: str, stamp_name: str = STAMP_NAME) -> bool:
    """Delete the modules' numba cache files in cache_dir unless its stamp (file ``stamp_name``) equals
    digest; write the stamp.

    Returns True when files were (or would have been) cleared: the stamp was missing or different.
    """
    stamp = cache_dir / stamp_name
    try:
        if stamp.read_text().strip() == digest:
            return False
    except OSError:
        pass
    prefixes = tuple(f'{stem}.' for stem in module_stems)
    try:
        entries = list(os.scandir(cache_dir))
    except OSError:
        return True
    for entry in entries:
        if entry.name.startswith(prefixes) and entry.name.endswith(('.nbi', '.nbc')):
            try:
                os.unlink(entry.path)
            except FileNotFoundError:
                pass  # another process cleared it first
            except OSError:
                pass  # not ours to delete (read-only cache): numba keeps using its own checks
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile('w', dir=cache_dir, prefix=stamp_name, delete=False) as handle:
            handle.write(digest + '\n')
        os.replace(handle.name, stamp)
    except OSError:
        pass
    return True


def guard_kernel_cache(package_dir: Path = PACKAGE_DIR, dependencies=DEPENDENCIES) -> bool:
    """Clear the package's cached kernels if any source they depend on changed since they were cached.

    Returns True when the cache was cleared (or had no stamp yet).
    """
    if os.environ.get('PPE_NUMBA_CACHE_GUARD', '1') == '0':
        return False
    modules = kernel_modules(package_dir)
    cache_dir = cache_directory()
    if cache_dir is None:
        return False
    return clear_stale_cache(
        cache_dir, [m.stem for m in modules], sources_digest(kernel_sources(package_dir, dependencies))
    )


def guard_module_cache(module: Path, dependencies: list[Path], cache_dir: Path | None) -> bool:
    """Clear one module's cached kernels in cache_dir (the files of its stem) when its source or a
    dependency's (a module whose njit helpers its kernels call or inline) changed since they were cached;
    the stamp is ``<stem>.`` + STAMP_NAME. For a kernel module outside this package (e.g.
    ppe_ros.core.boundary_join, which inlines ppe_ros.core.consolidation's helpers); returns True when
    cleared. ``PPE_NUMBA_CACHE_GUARD=0`` switches it off too."""
    if os.environ.get('PPE_NUMBA_CACHE_GUARD', '1') == '0' or cache_dir is None:
        return False
    module = Path(module)
    digest = sources_digest([module, *(Path(d) for d in dependencies)])
    return clear_stale_cache(cache_dir, [module.stem], digest, stamp_name=f'{module.stem}.{STAMP_NAME}')
