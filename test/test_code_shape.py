"""The shape of the code that review would otherwise have to check (issue 21)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'ppe_ros'

#: The longest a function outside the numba kernels may be (from ``def`` to its last line).
MAX_FUNCTION_LINES = 120
#: The longest a numba kernel of the PPE package (ppe_ros/core/ppe) may be, without its docstring: one screen.
MAX_PPE_KERNEL_LINES = 80


def _is_kernel(function: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    decorators = [ast.unparse(d) for d in function.decorator_list]
    return any('njit' in d or 'nb.jit' in d or 'intrinsic' in d for d in decorators)


def long_functions(root: Path, limit: int) -> list[str]:
    """``path:line name (n lines)`` of every function longer than ``limit`` lines that is not a numba kernel."""
    found = []
    for path in sorted(root.rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and not _is_kernel(node):
                lines = node.end_lineno - node.lineno + 1
                if lines > limit:
                    found.append(f'{path.relative_to(root.parent)}:{node.lineno} {node.name} ({lines} lines)')
    return found


def long_kernels(root: Path, limit: int) -> list[str]:
    """``path:line name (n lines)`` of every numba kernel longer than ``limit`` lines without its docstring."""
    found = []
    for path in sorted(root.rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.FunctionDef) and _is_kernel(node):
                lines = node.end_lineno - node.lineno + 1
                first = node.body[0]
                if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and len(node.body) > 1:
                    lines -= first.end_lineno - first.lineno + 1
                if lines > limit:
                    found.append(f'{path.relative_to(root.parent)}:{node.lineno} {node.name} ({lines} lines)')
    return found


def test_no_kernel_of_the_ppe_package_is_longer_than_a_screen():
    """Issue 18: the greedy's kernels are phases that each fit on a screen (the driver dispatches to them)."""
    assert long_kernels(PACKAGE / 'core' / 'ppe', MAX_PPE_KERNEL_LINES) == []


def test_the_kernel_length_check_finds_a_long_kernel_and_skips_docstrings(tmp_path):
    package = tmp_path / 'pkg'
    package.mkdir()
    body = '\n'.join(f'    x{i} = {i}' for i in range(10))
    doc = '    """' + '\n'.join(['line'] * 8) + '"""'
    (package / 'mod.py').write_text(
        f'@nb.njit(cache=True)\ndef long():\n{body}\n\n\n@nb.njit(cache=True)\ndef short():\n{doc}\n    x = 1\n'
    )
    assert long_kernels(package, 5) == ['pkg/mod.py:2 long (11 lines)']


def test_the_ppe_package_imports_no_private_names_from_outside():
    """Issue 18: the kernels PPE shares with other modules have public names (fitting's solve_sym3, fit_rays,
    ...); the package's own modules import each other's private names (one package, one cache guard)."""
    core = PACKAGE / 'core'
    offenders = []
    for path in [core / 'extraction.py', *sorted((core / 'ppe').glob('*.py'))]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and not (node.module or '').startswith('ppe_ros.core.ppe'):
                offenders += [f'{path.name}: {node.module}.{a.name}' for a in node.names if a.name.startswith('_')]
    assert offenders == []


def test_no_function_outside_the_numba_kernels_is_longer_than_120_lines():
    assert long_functions(PACKAGE, MAX_FUNCTION_LINES) == []


def test_the_length_check_finds_a_long_function_and_skips_kernels(tmp_path):
    package = tmp_path / 'pkg'
    package.mkdir()
    body = '\n'.join(f'    x{i} = {i}' for i in range(10))
    (package / 'mod.py').write_text(f'def long():\n{body}\n\n\n@nb.njit(cache=True)\ndef kernel():\n{body}\n')
    assert long_functions(package, 5) == ['pkg/mod.py:1 long (11 lines)']


def test_the_core_imports_nothing_of_ros():
    """ppe_ros.core is usable from plain Python with numpy and numba only."""
    offenders = []
    for path in sorted((PACKAGE / 'core').rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else ([node.module or ''] if isinstance(node, ast.ImportFrom) else [])
            )
            offenders += [
                f'{path.name}: {n}'
                for n in names
                if n.split('.')[0] in ('rclpy', 'rosbags') or n.startswith('ppe_ros.ros')
            ]
    assert offenders == []
