"""The paper's table (text and markdown), the targets check, the f-over-sqrt(e) plot and the machine description."""

from __future__ import annotations

import datetime as _dt
import math
import os
import platform
from collections.abc import Sequence
from pathlib import Path

from ppe_ros.benchmark.runner import Evaluation

COLUMNS = ('method', 'f %', 'k %', 'k all %', 'RMSE mm', 'n_o', 'n_u', 'n_m', 'n_s', 's/scan')

PAPER_PPE_ROW = {'f': 0.736, 'k': 0.779, 'rmse': 0.0145}
"""The paper's Table I, PPE on SynPEB (its "20 mm" level, most likely sigma = 14.1 mm)."""

RMSE_NOISE_TOLERANCE = 0.05
"""At sigma = 20 mm PPE's RMSE must be within 5 % of the noise."""

REPORT_END = '<!-- end of the ppe eval output: what follows is kept when ppe eval writes this file again -->'
"""Last line of the generated report; hand-written sections below it survive a re-run of ``ppe eval``."""

PPE_VARIANTS = ('ppe', 'ppe-paper')
"""Rows of this project's extractor (not competitors of each other in the targets)."""


def _number(value: float, scale: float = 1.0, digits: int = 1) -> str:
    if value is None or not math.isfinite(value):
        return '–'
    return f'{value * scale:.{digits}f}'


def table_cells(row: dict) -> list[str]:
    """The cells of one table row (f, k and k over all rays in %, RMSE in mm, counts per scan, seconds per scan)."""
    return [
        row['method'],
        _number(row['f'], 100),
        _number(row['k'], 100),
        _number(row.get('k_all_rays', math.nan), 100),
        _number(row['rmse'], 1000),
        _number(row['n_o']),
        _number(row['n_u']),
        _number(row['n_m']),
        _number(row['n_s']),
        _number(row['seconds'], digits=2),
    ]


def format_table(rows: Sequence[dict], *, markdown: bool = False) -> str:
    """The rows as an aligned text table or a markdown table."""
    cells = [list(COLUMNS)] + [table_cells(row) for row in rows]
    if markdown:
        lines = ['| ' + ' | '.join(cells[0]) + ' |', '|' + '|'.join(['---'] + ['---:'] * (len(COLUMNS) - 1)) + '|']
        lines += ['| ' + ' | '.join(row) + ' |' for row in cells[1:]]
        return '\n'.join(lines)
    widths = [max(len(row[i]) for row in cells) for i in range(len(COLUMNS))]
    return '\n'.join(
        '  '.join(cell.ljust(widths[i]) if i == 0 else cell.rjust(widths[i]) for i, cell in enumerate(row))
        for row in cells
    )


def group_title(group: str, rows: Sequence[dict], n_scans: int) -> str:
    """``sigma_14.1mm: radial sigma 14.1 mm, 30 scans``."""
    sigma = rows[0].get('radial_sigma') if rows else None
    noise = f'radial σ = {sigma * 1000:.1f} mm, ' if sigma is not None else ''
    return f'{group} ({noise}{n_scans} scan{"s" if n_scans != 1 else ""})'


def check_targets(evaluation: Evaluation, *, method: str = 'ppe') -> list[tuple[str, bool, str]]:
    """The issue's targets for one PPE row: ``(target, met, the numbers)`` per group with a known noise level.

    "Ahead" compares with every row that is not a PPE variant (:data:`PPE_VARIANTS`).
    """
    checks = []
    for group in evaluation.groups():
        rows = {row['method']: row for row in evaluation.rows(group)}
        if method not in rows or rows[method].get('radial_sigma') is None:
            continue
        ppe = rows[method]
        sigma = ppe['radial_sigma']
        name = f'σ = {sigma * 1000:.1f} mm'
        numbers = f'f {ppe["f"] * 100:.1f} %, k {ppe["k"] * 100:.1f} %, RMSE {ppe["rmse"] * 1000:.1f} mm'
        if abs(sigma - 0.01414) < 5e-4:
            met = (
                ppe['f'] >= PAPER_PPE_ROW['f']
                and ppe['k'] >= PAPER_PPE_ROW['k']
                and ppe['rmse'] <= PAPER_PPE_ROW['rmse']
            )
            checks.append((f"{name}: at least the paper's row (f 73.6 %, k 77.9 %, RMSE ≤ 14.5 mm)", met, numbers))
        if abs(sigma - 0.02) < 5e-4:
            met = (
                ppe['f'] >= PAPER_PPE_ROW['f']
                and ppe['k'] >= PAPER_PPE_ROW['k']
                and abs(ppe['rmse'] - sigma) <= RMSE_NOISE_TOLERANCE * sigma
            )
            checks.append((f'{name}: f ≥ 73.6 %, k ≥ 77.9 %, RMSE within 5 % of 20 mm (19.0–21.0 mm)', met, numbers))
        others = [row for name_, row in rows.items() if name_ not in PPE_VARIANTS]
        if others:
            behind = [row['method'] for row in others if not (ppe['f'] > row['f'] and ppe['k'] > row['k'])]
            versus = '; '.join(f'{row["method"]} f {row["f"] * 100:.1f} % k {row["k"] * 100:.1f} %' for row in others)
            checks.append(
                (
                    f'{name}: ahead of {", ".join(r["method"] for r in others)} on f and k',
                    not behind,
                    f'{method} f {ppe["f"] * 100:.1f} % k {ppe["k"] * 100:.1f} % vs {versus}',
                )
            )
    return checks


def machine_description() -> str:
    """CPU model, core count, OS, Python, numpy and numba versions."""
    import numba
    import numpy

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                cpu = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    return (
        f'{cpu}, {os.cpu_count()} cores visible, {platform.system()} {platform.release()}, '
        f'Python {platform.python_version()}, numpy {numpy.__version__}, numba {numba.__version__}'
    )


def plot_sweeps(
    path: str | os.PathLike[str],
    curves: dict[str, dict[float, float]],
    *,
    marks: dict[str, float] | None = None,
    title: str = 'PPE: f over sqrt(e)',
) -> Path:
    """PNG plot of f (%) over sqrt(e) (m), one line per noise level; ``marks`` = vertical lines (label -> e)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7.0, 4.2), dpi=120)
    for label, curve in curves.items():
        errors = sorted(curve)
        axes.plot([math.sqrt(e) for e in errors], [curve[e] * 100 for e in errors], marker='.', label=label)
    for label, e in (marks or {}).items():
        axes.axvline(math.sqrt(e), color='grey', linestyle='--', linewidth=0.8)
        axes.annotate(label, (math.sqrt(e), 2), rotation=90, fontsize=7, color='grey', ha='right', va='bottom')
    axes.set_xlabel('sqrt(e) [m]')
    axes.set_ylabel('f [%]')
    axes.set_ylim(0, 100)
    axes.set_xlim(0, 1.0)
    axes.grid(True, alpha=0.3)
    axes.set_title(title)
    axes.legend(fontsize=8)
    figure.tight_layout()
    out = Path(path)
    figure.savefig(out)
    plt.close(figure)
    return out


def markdown_report(
    evaluation: Evaluation,
    *,
    command: str,
    dataset_note: str,
    extra_groups: Sequence[str] = (),
    plot_name: str | None = None,
    notes: Sequence[str] = (),
    date: str | None = None,
) -> str:
    """The benchmark report as markdown (tables per group, targets, parameters, machine, date, command)."""
    when = date or _dt.datetime.now(_dt.UTC).strftime('%Y-%m-%d %H:%M UTC')
    lines = [
        '# Benchmarks',
        '',
        '<!-- Generated by `ppe eval` down to the end marker; do not edit that part by hand: re-run the command. -->',
        '',
        f'Generated {when} on {machine_description()}.',
        '',
        'Command:',
        '',
        '```',
        command,
        '```',
        '',
        dataset_note,
        '',
        'Metrics exactly as in the reference evaluation (Hoover et al., T = 0.8, strict `>`; ground-truth planes are '
        'the labels ≥ 10, or ≥ 1 for label files with 0 = unlabelled): **f** = correctly segmented GT planes / GT '
        'planes (summed over scans), **k** = fraction of labelled points in correctly segmented planes (mean over '
        "scans; the reference's denominator), **k all** = the same over all valid rays (the paper's formula), "
        '**RMSE** = radial residuals of the exact ray-length plane fit of every predicted segment, pooled '
        'over the points of planes with RMSE < 10 m, mean over scans; **n_o, n_u, n_m, n_s** = over-segmented, '
        'under-segmented, missed and spurious (noise) regions per scan; **s/scan** = wall time of the method per '
        'scan on this machine (loading and scoring excluded).',
        '',
    ]
    methods = ', '.join(f'`{m.describe()}`' for m in evaluation.methods)
    lines += [
        f'Methods: {methods}.',
        '',
        'Peers are optional extras, imported only when asked for: Open3D (`open3d`, `open3d-patches`) needs '
        '`make peers` (pip installs the pinned open3d, about 400 MB; on Debian/Ubuntu also '
        '`apt-get install libusb-1.0-0`); Polylidar3D '
        '(`polylidar`) has PyPI wheels for CPython ≤ 3.10 only. A peer that is not installed is skipped with '
        'the reason below.',
        '',
    ]
    for name, reason in evaluation.skipped.items():
        lines += [f'- **{name} skipped**: {reason}']
    if evaluation.skipped:
        lines.append('')

    present = {m.name for m in evaluation.methods}
    sections = [(name, check_targets(evaluation, method=name)) for name in PPE_VARIANTS if name in present]
    sections = [(name, checks) for name, checks in sections if checks]
    if sections:
        lines += ['## Targets (test split)', '']
        for name, checks in sections:
            if len(sections) > 1:
                lines += [f'`{name}`:', '']
            for target, met, numbers in checks:
                lines.append(f'- {"met" if met else "**NOT met**"}: {target} — {numbers}')
            lines.append('')

    main_groups = [g for g in evaluation.groups() if g not in extra_groups]
    if main_groups:
        lines += ['## Generated SynPEB-style scans', '']
        for group in main_groups:
            rows = evaluation.rows(group)
            n_scans = rows[0]['n_scans'] if rows else 0
            lines += [f'### {group_title(group, rows, n_scans)}', '', format_table(rows, markdown=True), '']
        if plot_name:
            lines += [
                f'![f over sqrt(e) per noise level]({plot_name})',
                '',
                f"PPE's f over sqrt(e) per noise level (one run per scan gives every e; lmax fixed), "
                f'[{plot_name}]({plot_name}).',
                '',
            ]
    extra = [g for g in evaluation.groups() if g in extra_groups]
    if extra:
        lines += [
            '## Shared real-format scans',
            '',
            'Each scan scored on its own with the same parameters (not tuned on them).',
            '',
        ]
        for group in extra:
            rows = evaluation.rows(group)
            lines += [f'### {group}', '', format_table(rows, markdown=True), '']
    for note in notes:
        lines += [note, '']
    return '\n'.join(lines).rstrip() + '\n\n' + REPORT_END + '\n'
