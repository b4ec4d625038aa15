"""``ppe eval DATASET``: run PPE, MSAC and the installed peers on a benchmark data set; print and write the table."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from ppe_ros.benchmark.dataset import MANIFEST_NAME, iter_scans, read_manifest
from ppe_ros.benchmark.methods import (
    ERROR_GRID,
    PPE_DEFAULT_MAX_ERROR_INCREMENT,
    PPE_DEFAULT_MAX_NEIGHBOR_DISTANCE,
    make_method,
    method_names,
)
from ppe_ros.commands._options import non_negative_float, positive_float
from ppe_ros.io.files import refuse_overwriting_inputs, write_file_atomically
from ppe_ros.io.loading import scan_input_files

DEFAULT_METHODS = ('ppe', 'msac', 'open3d', 'open3d-patches', 'polylidar')
DEFAULT_OUT = Path('docs') / 'benchmarks.md'


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'eval',
        help='benchmark PPE against MSAC and peers on a data set',
        description='Run the methods on a data set made by `ppe dataset make` (and on extra labelled scans), score '
        "them with the paper's metrics and print the paper's table per noise level (f %, k %, k over all rays "
        '%, RMSE mm, n_o, n_u, n_m, n_s, seconds per scan). Writes the tables as markdown (with the command, the '
        "machine and the date) and a PNG of PPE's f over sqrt(e) per noise level. Methods whose optional package "
        'is missing are skipped with the reason.',
    )
    parser.add_argument('dataset', help='data set directory (with dataset.json)')
    parser.add_argument(
        '--methods',
        nargs='+',
        default=None,
        metavar='NAME',
        help=f'methods to run (default: {" ".join(DEFAULT_METHODS)}, after ppe-lidar on a lidar data set and '
        f'ppe-depth-camera on a depth camera one; known: {" ".join(method_names())})',
    )
    parser.add_argument('--split', choices=('train', 'test'), default='test', help='split to evaluate (default test)')
    parser.add_argument(
        '--noise',
        type=float,
        nargs='+',
        default=None,
        metavar='MM',
        help='radial noise levels in mm to evaluate, e.g. 14.1 20 (default: all levels)',
    )
    parser.add_argument('--max-scans', type=int, default=None, metavar='N', help='at most N scans per level')
    parser.add_argument(
        '--params',
        nargs='+',
        default=[],
        metavar='[MM=]YAML',
        help='PPE parameters from params files (as written by `ppe tune`): a plain YAML applies to '
        'every scan, MM=YAML only to the noise level of radial sigma MM mm (e.g. --params '
        'tuned_14.1mm.yaml 20=tuned_20mm.yaml)',
    )
    parser.add_argument(
        '--lmax',
        type=positive_float,
        default=None,
        help=f'PPE lmax in m (default {PPE_DEFAULT_MAX_NEIGHBOR_DISTANCE}, or from a plain --params; '
        'MM=YAML levels keep theirs)',
    )
    parser.add_argument(
        '-e',
        '--max-error-increment',
        type=non_negative_float,
        default=None,
        metavar='E',
        help=f'PPE e in m^2 (default {PPE_DEFAULT_MAX_ERROR_INCREMENT}, or from a plain --params; '
        'MM=YAML levels keep theirs)',
    )
    parser.add_argument('--msac-distance', type=positive_float, default=0.034, help='MSAC/Open3D inlier distance (m)')
    parser.add_argument(
        '--msac-fraction',
        type=float,
        default=0.03,
        help='MSAC/Open3D: stop when this fraction of the points is left (default 0.03)',
    )
    parser.add_argument('--seed', type=int, default=0, help='seed of the random methods (default 0)')
    parser.add_argument(
        '--extra',
        nargs='+',
        default=[],
        metavar='SCAN',
        help='also score these labelled scan files, each on its own '
        '(e.g. ../shared/data/synpeb/pc_01.pcd ../shared/data/icl_nuim/icl_nuim_0.png)',
    )
    parser.add_argument('--out', default=str(DEFAULT_OUT), help=f'markdown output (default {DEFAULT_OUT})')
    parser.add_argument('--plot', default=None, help='PNG of f over sqrt(e) (default: OUT with .png suffix)')
    parser.add_argument(
        '--raw',
        default=None,
        metavar='JSON',
        help='also write every per-scan result as JSON (updated after each scan: an interrupted run '
        'resumes with --reuse JSON)',
    )
    parser.add_argument(
        '--reuse',
        default=None,
        metavar='JSON',
        help='take the results of methods with unchanged parameters from an earlier --raw file '
        'instead of running them again (e.g. after tuning PPE only)',
    )
    parser.add_argument('--no-sweep', action='store_true', help='skip the f-over-sqrt(e) sweep and plot')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')
    parser.set_defaults(func=run)


def split_params_argument(entry: str) -> tuple[float | None, str]:
    """``'20=tuned.yaml'`` -> (0.020 m, 'tuned.yaml'); ``'tuned.yaml'`` -> (None, 'tuned.yaml').

    Raises:
        ValueError: ``MM=`` that is not a non-negative number of millimetres.
    """
    head, sep, tail = entry.partition('=')
    if not sep:
        return None, entry
    try:
        sigma_mm = float(head)
    except ValueError:
        raise ValueError(f'--params {entry!r}: expected YAML or MM=YAML with MM the radial sigma in mm') from None
    if not (sigma_mm >= 0.0 and sigma_mm < float('inf')) or not tail:
        raise ValueError(f'--params {entry!r}: expected YAML or MM=YAML with MM the radial sigma in mm')
    return sigma_mm / 1000.0, tail


def ppe_parameters(args: argparse.Namespace) -> tuple[float, float, dict[float, tuple[float, float]]]:
    """(lmax, e, per-level {sigma m: (lmax, e)}): command line, else a plain --params, else the reference's values.

    Raises:
        ValueError: more than one plain --params file.
    """
    from ppe_ros.benchmark.tuning import read_params_yaml

    lmax, error = PPE_DEFAULT_MAX_NEIGHBOR_DISTANCE, PPE_DEFAULT_MAX_ERROR_INCREMENT
    entries = [split_params_argument(entry) for entry in args.params]
    plain = [path for sigma, path in entries if sigma is None]
    if len(plain) > 1:
        raise ValueError(f'at most one --params file without MM= (for every scan); got {", ".join(plain)}')
    if plain:
        params = read_params_yaml(plain[0])
        lmax = params.get('max_neighbor_distance', lmax)
        error = params.get('max_error_increment', error)
    if args.lmax is not None:
        lmax = args.lmax
    if args.max_error_increment is not None:
        error = args.max_error_increment
    levels = {}
    for sigma, path in entries:
        if sigma is not None:
            params = read_params_yaml(path)
            levels[sigma] = (params.get('max_neighbor_distance', lmax), params.get('max_error_increment', error))
    return lmax, error, levels


def canonical_command(args: argparse.Namespace) -> str:
    """The command line that reproduces this run (every option explicit)."""
    parts = ['ppe', 'eval', args.dataset, '--methods', *args.methods, '--split', args.split]
    if args.noise:
        parts += ['--noise', *(f'{v:g}' for v in args.noise)]
    if args.max_scans is not None:
        parts += ['--max-scans', str(args.max_scans)]
    if args.params:
        parts += ['--params', *args.params]
    if args.lmax is not None:
        parts += ['--lmax', f'{args.lmax:g}']
    if args.max_error_increment is not None:
        parts += ['-e', f'{args.max_error_increment:g}']
    if args.msac_distance != 0.034:
        parts += ['--msac-distance', f'{args.msac_distance:g}']
    if args.msac_fraction != 0.03:
        parts += ['--msac-fraction', f'{args.msac_fraction:g}']
    if args.seed:
        parts += ['--seed', str(args.seed)]
    if args.extra:
        parts += ['--extra', *args.extra]
    parts += ['--out', args.out]
    if args.plot:
        parts += ['--plot', args.plot]
    if args.no_sweep:
        parts.append('--no-sweep')
    if args.reuse:
        parts += ['--reuse', args.reuse]
    return shlex.join(parts)


def default_methods(kind: str) -> tuple[str, ...]:
    """The methods ``ppe eval`` runs on a data set of this kind (its manifest's ``kind``) without --methods: the
    sensor profile of generated lidar sweeps or depth frames first, then DEFAULT_METHODS."""
    profile = {'lidar': ('ppe-lidar',), 'depth_camera': ('ppe-depth-camera',)}.get(kind, ())
    return (*profile, *DEFAULT_METHODS)


def build_methods(
    args: argparse.Namespace, lmax: float, error: float, levels: dict[float, tuple[float, float]] | None = None
) -> list:
    methods = []
    for name in dict.fromkeys(args.methods):
        if name == 'ppe':
            methods.append(
                make_method(
                    'ppe',
                    max_neighbor_distance=lmax,
                    max_error_increment=error,
                    sweep_errors=None if args.no_sweep else ERROR_GRID,
                    level_params=levels,
                )
            )
        elif name in ('msac', 'open3d'):
            methods.append(make_method(name, distance=args.msac_distance, fraction=args.msac_fraction, seed=args.seed))
        else:
            methods.append(make_method(name))
    return methods


def dataset_note(directory: str, manifest: dict, split: str) -> str:
    scans = [s for s in manifest['scans'] if s['split'] == split]
    planes = [s['n_planes'] for s in scans]
    levels = ', '.join(f'{lv["radial_sigma"] * 1000:.1f}' for lv in manifest['levels'])
    mean_planes = sum(planes) / len(planes) if planes else float('nan')
    kind = manifest.get('kind', 'synpeb')
    if kind != 'synpeb':
        grid = f'{manifest["rows"]} x {manifest["cols"]}' if manifest.get('rows') else f'{manifest["cols"]}-column'
        make = (
            f'ppe dataset make {directory} --kind {kind} --seed {manifest["seed"]} --train {manifest["n_train"]} '
            f'--test {manifest["n_test"]}'
        )
        what = 'lidar sweeps of streets' if kind == 'lidar' else 'depth-camera frames of rooms'
        return (
            f'Data set: `{make}` (generated {what} with realistic sensor errors, {grid} grid, levels '
            f'{", ".join(lv["name"] for lv in manifest["levels"])}, {manifest["n_train"]} train + '
            f'{manifest["n_test"]} test scans per level, {mean_planes:.1f} GT surfaces per {split} scan on '
            f'average; GT = one label per planar surface, clutter unlabelled). Split evaluated: **{split}**.'
        )
    make = (
        f'ppe dataset make {directory} --seed {manifest["seed"]} --train {manifest["n_train"]} '
        f'--test {manifest["n_test"]} --rows {manifest["rows"]} --cols {manifest["cols"]}'
    )
    return (
        f'Data set: `{make}` (generated SynPEB-style rooms, {manifest["rows"]} x {manifest["cols"]} grid, '
        f'radial σ = {levels} mm, angular σ = {manifest["angular_sigma_deg"] * 1000:g} mdeg, '
        f'{manifest["n_train"]} train + {manifest["n_test"]} test scans per level, {mean_planes:.1f} GT planes per '
        f'{split} scan on average). Split evaluated: **{split}**.'
    )


def kept_after_report(path: Path) -> str:
    """The part of an existing report after :data:`REPORT_END` (kept when the report is written again)."""
    from ppe_ros.benchmark.report import REPORT_END

    try:
        text = path.read_text()
    except FileNotFoundError:
        return ''
    _, sep, tail = text.partition(REPORT_END + '\n')
    return tail if sep else ''


def _check_run_arguments(args: argparse.Namespace) -> tuple[Path, Path]:
    """Refuse unknown methods, a bad ``--max-scans`` and outputs in a missing folder or overwriting inputs.

    Returns the report path and the plot path.
    """
    unknown = [m for m in args.methods if m not in method_names()]
    if unknown:
        raise ValueError(f'unknown method(s) {", ".join(unknown)}; known: {", ".join(method_names())}')
    if args.max_scans is not None and args.max_scans < 1:
        raise ValueError(f'--max-scans must be >= 1; got {args.max_scans}')
    out = Path(args.out)
    plot = Path(args.plot) if args.plot else out.with_suffix('.png')
    for path in (out, plot, *([Path(args.raw)] if args.raw else [])):
        if not path.parent.is_dir():
            raise FileNotFoundError(f'output folder {path.parent} does not exist')
    # outputs must not be inputs, compared by device and inode (a hard or symbolic link is the input)
    inputs = [path for scan in args.extra for path in scan_input_files(scan)]
    inputs += [Path(path) for _, path in map(split_params_argument, args.params)]
    inputs += [Path(args.dataset) / MANIFEST_NAME]
    inputs += [
        entry.path
        for entry in iter_scans(args.dataset, split=args.split, noise_mm=args.noise, max_scans=args.max_scans)
    ]
    raw = [Path(args.raw)] if args.raw else []
    refuse_overwriting_inputs([out, plot, *raw], inputs)
    if args.reuse:  # --raw may be the --reuse file (an interrupted run resumes), the report may not
        refuse_overwriting_inputs([out, plot], [args.reuse])
    return out, plot


def _report_notes(args: argparse.Namespace, evaluation, previous, curves: dict) -> list[str]:
    """The notes of the report: the results reused from ``--reuse``, the s/scan of ``ppe`` and its sweep."""
    notes = []
    if previous:
        reused = sorted({r.method for r in evaluation.results if any(r is p for p in previous.values())})
        if reused:
            notes.append(
                f'Results of {", ".join(reused)} were taken from the earlier run {args.reuse} (same data, '
                f'same parameters; their s/scan were measured in that run).'
            )
    if curves:
        best = []
        for group, curve in curves.items():
            e_best = max(curve, key=lambda e: (curve[e], -e))
            best.append(f'{group}: best f {curve[e_best] * 100:.1f} % at sqrt(e) = {e_best**0.5:.2f} m')
        single = (
            ' `ppe-paper` runs a single extraction at its e without a sweep: its s/scan is the time of one extraction.'
            if any(m.name == 'ppe-paper' for m in evaluation.methods)
            else ''
        )
        notes.append(
            "`ppe`'s s/scan include running its hierarchy on to the largest e of the sweep (1 m²) and "
            'cutting it at every e.' + single
        )
        notes.append(
            '`ppe` sweep over the e grid (lmax as in the table; best e chosen on the evaluated split, for '
            'information only — parameters are tuned on the train split with `ppe tune`): ' + '; '.join(best) + '.'
        )
    return notes


def run(args: argparse.Namespace) -> int:
    from ppe_ros.benchmark.report import format_table, markdown_report, plot_sweeps
    from ppe_ros.benchmark.runner import (
        available_methods,
        dataset_scans,
        evaluate,
        load_labelled_scan,
        load_previous_results,
    )

    manifest = read_manifest(args.dataset)
    if args.methods is None:
        args.methods = list(default_methods(manifest.get('kind', 'synpeb')))
    out, plot = _check_run_arguments(args)
    previous = load_previous_results(args.reuse) if args.reuse else None
    lmax, error, levels = ppe_parameters(args)
    methods = build_methods(args, lmax, error, levels)

    extra_groups, scans = [], []
    for path in args.extra:  # the few extra scans first, then the data set level by level
        name = Path(path).name
        extra_groups.append(name)
        scans.append((name, lambda path=path, name=name: load_labelled_scan(path, name=name, group=name)))
    scans += dataset_scans(args.dataset, split=args.split, noise_mm=args.noise, max_scans=args.max_scans)
    if not scans:
        raise ValueError(f'no {args.split} scans in {args.dataset} for the chosen noise levels')

    def save_raw(evaluation) -> None:
        partial = Path(args.raw).with_name(Path(args.raw).name + '.part')
        partial.write_text(json.dumps(evaluation.to_dict(), indent=1, default=float) + '\n')
        partial.replace(args.raw)

    bar = None
    if not args.quiet:
        from tqdm import tqdm

        usable, _ = available_methods(methods)  # skipped methods do not run: not in the bar's total
        bar = tqdm(total=len(scans) * len(usable), unit='run', file=sys.stderr, desc='ppe eval')
    try:
        evaluation = evaluate(
            scans,
            methods,
            previous=previous,
            checkpoint=save_raw if args.raw else None,
            progress=(lambda text: (bar.set_postfix_str(text), bar.update(1))) if bar else None,
        )
    finally:
        if bar is not None:
            bar.close()
    for name, reason in evaluation.skipped.items():
        print(f'skipped {name}: {reason}', file=sys.stderr)

    for group in evaluation.groups():
        rows = evaluation.rows(group)
        print(f'\n{group} ({rows[0]["n_scans"] if rows else 0} scans)')
        print(format_table(rows))

    curves = {}
    if not args.no_sweep:
        for group in evaluation.groups():
            if group in extra_groups:
                continue
            curve = evaluation.sweep_curve(group)
            if curve:
                curves[group] = curve
    plot_name = None
    if curves:
        marks = {f'e = {error:g} m²': error}
        for sigma, (_, level_error) in levels.items():
            if level_error != error:
                marks[f'e = {level_error:g} m² (σ {sigma * 1000:g} mm)'] = level_error
        lmaxes = {lmax, *(level_lmax for level_lmax, _ in levels.values())}
        lmax_text = f'lmax = {lmax:g} m' if len(lmaxes) == 1 else 'lmax per level as in the tables'
        plot_sweeps(plot, curves, marks=marks, title=f'PPE on the {args.split} split: f over sqrt(e) ({lmax_text})')
        plot_name = plot.name if plot.parent.resolve() == out.parent.resolve() else str(plot)
    notes = _report_notes(args, evaluation, previous, curves)
    text = markdown_report(
        evaluation,
        command=canonical_command(args),
        dataset_note=dataset_note(args.dataset, manifest, args.split),
        extra_groups=extra_groups,
        plot_name=plot_name,
        notes=notes,
    )
    report = (text + kept_after_report(out)).encode('utf-8')
    write_file_atomically(out, lambda stream: stream.write(report), overwrite=True)
    print(f'\nwrote {out}' + (f' and {plot}' if plot_name else ''))
    if args.raw:
        save_raw(evaluation)
        print(f'wrote {args.raw}')
    return 0
