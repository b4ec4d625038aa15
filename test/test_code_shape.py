"""The shape of the code that review would otherwise have to check (issue 21)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'ppe_ros'

#: The longest a function outside the numba kernels may be (from ``def`` to its last line).
MAX_FUNCTION_LINES = 120


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
