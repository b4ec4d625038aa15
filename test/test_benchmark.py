"""Benchmark suite: data set making, methods, evaluation, report, tuning and the eval/tune/dataset commands."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from ppe_ros.benchmark import dataset as ds
from ppe_ros.benchmark.methods import (
    ERROR_GRID,
    MethodUnavailable,
    MsacMethod,
    PpeMethod,
    PpePaperMethod,
    make_method,
    method_names,
)
from ppe_ros.benchmark.report import REPORT_END, check_targets, format_table
from ppe_ros.benchmark.runner import (
    Evaluation,
    LabelledScan,
    ScanResult,
    available_methods,
    evaluate,
    run_method_on_scan,
)
from ppe_ros.benchmark.tuning import params_yaml, read_params_yaml, tune_ppe, write_params_yaml
from ppe_ros.cli import main
from ppe_ros.core.evaluation import score_segmentation
from ppe_ros.core.synthetic import plane_scan
from ppe_ros.io import load_scan, read_pcd

TINY = {'rows': 24, 'cols': 32, 'n_train': 1, 'n_test': 2, 'sigmas': (0.0, 0.02)}


@pytest.fixture(scope='module')
def tiny_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp('bench') / 'data'
    ds.make_dataset(root, seed=4, **TINY)
    return root


# ----------------------------------------------------------------------------- data sets


def test_level_names_follow_the_synpeb_variances():
    assert [ds.level_name(s) for s in ds.DEFAULT_SIGMAS] == [
        'sigma_0mm',
        'sigma_7.1mm',
        'sigma_10mm',
        'sigma_14.1mm',
        'sigma_20mm',
    ]
    assert np.allclose(np.square(np.array(ds.DEFAULT_SIGMAS) * 100), [0, 0.5, 1, 2, 4])


def test_synpeb_grid_is_synpebs_at_500():
    grid = ds.synpeb_grid(500, 500)
    assert np.allclose(grid.azimuth_deg, -35.0 + 0.14 * np.arange(500))
    assert grid.elevation_deg[0] == 30.0 and grid.elevation_deg[-1] == -30.0


def test_dataset_is_written_in_synpeb_format(tiny_dataset):
    manifest = ds.read_manifest(tiny_dataset)
    assert [lv['name'] for lv in manifest['levels']] == ['sigma_0mm', 'sigma_20mm']
    assert len(manifest['scans']) == (1 + 2) * 2
    path = tiny_dataset / 'test' / 'sigma_20mm' / 'pc_02.pcd'
    cloud = read_pcd(path)
    assert list(cloud.header.fields) == ['x', 'y', 'z', 'intensity']
    assert (cloud.header.width, cloud.header.height) == (32, 24)
    assert cloud.header.encoding == 'binary_compressed'
    assert all(cloud.data.dtype[name] == np.float32 for name in ('x', 'y', 'z', 'intensity'))
    scan = load_scan(path)
    assert scan.meta['min_plane_label'] == 10
    valid = scan.valid
    labels = scan.labels[valid]
    assert np.all((labels >= 10) | (labels == 3)) and np.all(scan.labels[~valid] == 0)  # 3: a too-small face piece
    assert np.count_nonzero(labels >= 10) > 0.9 * labels.size
    assert len(np.unique(labels[labels >= 10])) >= 5
    assert manifest['min_region_pixels'] == 4


def test_levels_share_scenes_and_noise_is_as_asked(tiny_dataset):
    clean = load_scan(tiny_dataset / 'test' / 'sigma_0mm' / 'pc_01.pcd')
    noisy = load_scan(tiny_dataset / 'test' / 'sigma_20mm' / 'pc_01.pcd')
    assert np.array_equal(clean.labels, noisy.labels)
    both = clean.valid & noisy.valid
    diff = np.linalg.norm(noisy.points[both], axis=1) - np.linalg.norm(clean.points[both], axis=1)
    assert 0.012 < diff.std() < 0.028  # radial sigma 20 mm (768 samples)
    train = load_scan(tiny_dataset / 'train' / 'sigma_0mm' / 'pc_01.pcd')
    assert not np.array_equal(train.labels, clean.labels)  # train and test scenes differ


def test_dataset_is_deterministic(tmp_path, tiny_dataset):
    again = tmp_path / 'again'
    ds.make_dataset(again, seed=4, **TINY)
    for entry in ds.read_manifest(tiny_dataset)['scans']:
        assert (again / entry['file']).read_bytes() == (tiny_dataset / entry['file']).read_bytes()
    other = tmp_path / 'other'
    ds.make_dataset(other, seed=5, **TINY)
    name = 'test/sigma_0mm/pc_01.pcd'
    assert (other / name).read_bytes() != (tiny_dataset / name).read_bytes()


def test_dataset_refuses_to_overwrite(tiny_dataset):
    with pytest.raises(FileExistsError, match='already holds a data set'):
        ds.make_dataset(tiny_dataset, **TINY)


@pytest.mark.parametrize(
    ('kwargs', 'message'),
    [
        ({'sigmas': ()}, 'sigmas'),
        ({'sigmas': (0.01, 0.01001)}, 'differ'),
        ({'n_train': -1}, 'n_train'),
        ({'n_train': 0, 'n_test': 0}, 'at least one'),
        ({'rows': 1}, 'rows'),
        ({'seed': -2}, 'seed'),
    ],
)
def test_dataset_bad_parameters(tmp_path, kwargs, message):
    with pytest.raises(ValueError, match=message):
        ds.make_dataset(tmp_path / 'x', **{**TINY, **kwargs})


def test_iter_scans_selects_split_and_level(tiny_dataset):
    scans = list(ds.iter_scans(tiny_dataset, split='test', noise_mm=[20]))
    assert [s.name for s in scans] == ['test/sigma_20mm/pc_01', 'test/sigma_20mm/pc_02']
    assert all(s.radial_sigma == 0.02 for s in scans)
    assert len(list(ds.iter_scans(tiny_dataset, split='train', max_scans=1))) == 2
    with pytest.raises(ValueError, match=r'no noise level of 14\.1 mm'):
        list(ds.iter_scans(tiny_dataset, noise_mm=[14.1]))
    with pytest.raises(FileNotFoundError, match='not a data set'):
        ds.read_manifest(tiny_dataset / 'test')


# ----------------------------------------------------------------------------- methods


def test_ppe_and_msac_segment_a_simple_scene():
    scan = plane_scan(3, rows=24, cols=32, radial_sigma=0.002, seed=1)
    for method in (
        PpeMethod(max_neighbor_distance=0.5, max_error_increment=0.01),
        MsacMethod(distance=0.01, fraction=0.0),
    ):
        result = method.segment(scan.points)
        assert result.labels.shape == scan.labels.shape and result.seconds > 0
        assert score_segmentation(result.labels, scan.labels).f == 1.0, method.name


def test_ppe_sweep_gives_every_cut_of_one_run():
    scan = plane_scan(3, rows=24, cols=32, radial_sigma=0.002, seed=1)
    method = PpeMethod(max_neighbor_distance=0.5, max_error_increment=0.01, sweep_errors=[0.0, 0.01, 1.0])
    result = method.segment(scan.points)
    assert set(result.sweep) == {0.0, 0.01, 1.0}
    assert np.count_nonzero(result.sweep[0.0]) < np.count_nonzero(result.sweep[0.01])  # e = 0: few joins
    same = score_segmentation(result.sweep[0.01], scan.labels)
    assert same.n_correct == score_segmentation(result.labels, scan.labels).n_correct == 3
    # residuals (m) of the exact radial fits: on every plane pixel and nowhere else, at the noise level (2 mm); a
    # single pixel may sit far off (e = 0.01 m^2 admits joins of up to 0.1 m), so the bound is on the RMSE
    assert np.array_equal(np.isfinite(result.residuals), result.labels > 0)
    assert np.sqrt(np.nanmean(result.residuals**2)) < 0.005


def test_ppe_level_params_apply_to_their_noise_level_only():
    scan = plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=1)
    # lmax 1 mm joins nothing on this grid: a default that finds no plane; the 5 mm level's parameters find all 3
    method = PpeMethod(max_neighbor_distance=0.001, max_error_increment=0.01, level_params={0.005: (0.5, 0.005)})
    assert method.for_noise(0.005).max_neighbor_distance == 0.5
    assert method.for_noise(0.00504).max_neighbor_distance == 0.5  # within 0.05 mm
    assert method.for_noise(0.02) is method and method.for_noise(None) is method
    assert method.parameters()['at 5 mm'] == {'lmax': 0.5, 'e': 0.005, 'sqrt_e': math.sqrt(0.005)}
    assert 'at 5 mm={lmax=0.5' in method.describe()

    def labelled(sigma):
        return LabelledScan(
            name='s',
            points=scan.points,
            origins=None,
            labels=scan.labels,
            gt_min_label=10,
            group='g',
            radial_sigma=sigma,
        )

    assert run_method_on_scan(method, labelled(0.005)).score.n_correct == 3
    assert run_method_on_scan(method, labelled(None)).score.n_correct == 0
    with pytest.raises(ValueError, match='two entries'):
        PpeMethod(level_params={0.02: (0.1, 0.01), 0.02001: (0.2, 0.01)})
    with pytest.raises(ValueError, match='radial sigma'):
        PpeMethod(level_params={-0.01: (0.1, 0.01)})


def test_ppe_paper_is_ppe_with_the_reference_parameters():
    method = make_method('ppe-paper')
    assert isinstance(method, PpePaperMethod) and method.name == 'ppe-paper' and 'ppe-paper' in method_names()
    assert (method.max_neighbor_distance, method.max_error_increment, method.sweep_errors) == (0.18, 0.0484, None)


def test_method_registry_and_unavailable_peers(monkeypatch):
    assert {'ppe', 'msac', 'open3d', 'polylidar'} <= set(method_names())
    with pytest.raises(ValueError, match='unknown method'):
        make_method('nope')
    import ppe_ros.benchmark.peers as peers

    def missing(name):
        raise ImportError(f'No module named {name!r}')

    monkeypatch.setattr(peers.importlib, 'import_module', missing)
    usable, skipped = available_methods([make_method('msac'), make_method('open3d'), make_method('polylidar')])
    assert [m.name for m in usable] == ['msac']
    assert 'make peers' in skipped['open3d']
    assert 'no wheel for this Python' in skipped['polylidar']
    with pytest.raises(MethodUnavailable):
        make_method('open3d').segment(np.zeros((2, 2, 3)))


# ----------------------------------------------------------------------------- evaluation and report


def _scan_loader(seed: int, group: str):
    scan = plane_scan(3, rows=24, cols=32, radial_sigma=0.005, seed=seed)
    return (
        f'scan{seed}',
        lambda: LabelledScan(
            name=f'scan{seed}',
            points=scan.points,
            origins=None,
            labels=scan.labels,
            gt_min_label=10,
            group=group,
            radial_sigma=0.005,
        ),
    )


def test_evaluate_scores_every_method_on_every_scan():
    methods = [
        PpeMethod(max_neighbor_distance=0.5, max_error_increment=0.005, sweep_errors=ERROR_GRID[:5]),
        MsacMethod(distance=0.02, fraction=0.0),
    ]
    evaluation = evaluate([_scan_loader(1, 'a'), _scan_loader(2, 'a')], methods, warm_up=False)
    assert len(evaluation.results) == 4
    rows = evaluation.rows('a')
    assert [r['method'] for r in rows] == ['ppe', 'msac']
    assert rows[0]['n_scans'] == 2 and rows[0]['f'] == 1.0
    assert 0.004 < rows[0]['rmse'] < 0.006  # radial sigma 5 mm
    curve = evaluation.sweep_curve('a')
    assert sorted(curve) == sorted(ERROR_GRID[:5]) and max(curve.values()) == 1.0
    table = format_table(rows)
    assert 'f %' in table.splitlines()[0] and '100.0' in table
    json.dumps(evaluation.to_dict(), default=float)


def _fake_row(method, f, k, rmse, sigma):
    score = score_segmentation(np.zeros((2, 2), int), np.full((2, 2), 10))
    score = score.__class__(**{**score.__dict__, 'f': f, 'k': k, 'rmse': rmse, 'n_correct': round(f * 10), 'n_gt': 10})
    return ScanResult(scan='s', group=f'g{sigma}', method=method, score=score, seconds=1.0, radial_sigma=sigma)


def test_targets_are_checked_with_the_numbers():
    results = [
        _fake_row('ppe', 0.8, 0.8, 0.0140, 0.01414),
        _fake_row('msac', 0.1, 0.4, 0.02, 0.01414),
        _fake_row('ppe', 0.7, 0.9, 0.0205, 0.02),
        _fake_row('msac', 0.75, 0.5, 0.02, 0.02),
    ]
    evaluation = Evaluation(results=results, skipped={}, methods=[PpeMethod(), MsacMethod()])
    checks = check_targets(evaluation)
    met = {target.split(':')[0] + ':' + target.split(':')[1][:6]: ok for target, ok, _ in checks}
    assert met == {
        'σ = 14.1 mm: at le': True,
        'σ = 14.1 mm: ahead': True,
        'σ = 20.0 mm: f ≥ 7': False,
        'σ = 20.0 mm: ahead': False,
    }
    assert any('f 70.0 %' in numbers for _, _, numbers in checks)


def test_ppe_variants_are_not_competitors_in_the_targets():
    results = [
        _fake_row('ppe', 0.8, 0.8, 0.0140, 0.01414),
        _fake_row('ppe-paper', 0.9, 0.9, 0.0140, 0.01414),
        _fake_row('msac', 0.1, 0.4, 0.02, 0.01414),
    ]
    evaluation = Evaluation(results=results, skipped={}, methods=[PpeMethod(), PpePaperMethod(), MsacMethod()])
    ahead = [(target, ok) for target, ok, _ in check_targets(evaluation) if 'ahead of' in target]
    assert ahead == [('σ = 14.1 mm: ahead of msac on f and k', True)]  # ppe-paper beats ppe but is not a rival
    paper = check_targets(evaluation, method='ppe-paper')
    assert any('f 90.0 %' in numbers for _, _, numbers in paper)


# ----------------------------------------------------------------------------- tuning and params files


def test_params_yaml_is_a_node_params_file(tmp_path):
    path = write_params_yaml(tmp_path / 'p.yaml', 0.18, 0.0484, comments=['tuned'])
    data = yaml.safe_load(path.read_text())
    assert data == {'extractor': {'ros__parameters': {'max_error_increment': 0.0484, 'max_neighbor_distance': 0.18}}}
    assert read_params_yaml(path) == {'max_error_increment': 0.0484, 'max_neighbor_distance': 0.18}
    with pytest.raises(FileExistsError):
        write_params_yaml(path, 0.1, 0.01)
    assert params_yaml(0.1, 0.01).startswith('extractor:')


def test_read_params_yaml_reads_the_node_config_and_rejects_junk(tmp_path):
    from pathlib import Path

    config = Path(__file__).resolve().parents[1] / 'config' / 'extractor.yaml'
    params = read_params_yaml(config)
    assert params == {'max_neighbor_distance': math.inf, 'max_error_increment': 0.01}  # 0: sensor none's
    bad = tmp_path / 'bad.yaml'
    bad.write_text('extractor:\n  ros__parameters:\n    max_error_increment: lots\n')
    with pytest.raises(ValueError, match='must be a number'):
        read_params_yaml(bad)
    bad.write_text('- 1\n')
    with pytest.raises(ValueError, match='mapping'):
        read_params_yaml(bad)


def test_tune_ppe_finds_a_working_point():
    loaders = [_scan_loader(1, 't')[1], _scan_loader(2, 't')[1]]
    result = tune_ppe(loaders, lmax_grid=(0.001, 0.5), error_grid=(0.0, 0.01, 0.05))
    assert result.scores.shape == (2, 3)
    assert np.all(result.scores[0] == 0.0)  # lmax 1 mm joins nothing
    assert result.best_lmax == 0.5 and result.best_score == 1.0
    assert result.best_error == 0.01  # first of the tied best e values
    with pytest.raises(ValueError, match='lmax grid'):
        tune_ppe(loaders, lmax_grid=())


# ----------------------------------------------------------------------------- commands


def test_dataset_command(tmp_path, capsys):
    out = tmp_path / 'd'
    assert (
        main(
            [
                'dataset',
                'make',
                str(out),
                '--scans',
                '1',
                '--rows',
                '12',
                '--cols',
                '16',
                '--noise',
                '0',
                '20',
                '--quiet',
            ]
        )
        == 0
    )
    assert '4 scans' in capsys.readouterr().out
    assert len(list(out.glob('*/*/*.pcd'))) == 4
    assert main(['dataset', 'make', str(out), '--scans', '1', '--quiet']) == 2  # refuses an existing data set
    assert 'already holds a data set' in capsys.readouterr().err


def test_eval_command_end_to_end(tiny_dataset, tmp_path, capsys):
    out = tmp_path / 'bench.md'
    raw = tmp_path / 'raw.json'
    code = main(
        [
            'eval',
            str(tiny_dataset),
            '--methods',
            'ppe',
            'msac',
            'polylidar',
            '--noise',
            '20',
            '--out',
            str(out),
            '--raw',
            str(raw),
            '--quiet',
            '--lmax',
            '0.5',
        ]
    )
    assert code == 0
    captured = capsys.readouterr()
    assert 'sigma_20mm (2 scans)' in captured.out and 'RMSE mm' in captured.out
    text = out.read_text()
    assert '| method | f % | k % | k all % | RMSE mm | n_o | n_u | n_m | n_s | s/scan |' in text
    assert 'ppe eval ' in text and '--lmax 0.5' in text and 'Generated ' in text and 'cores' in text
    assert '| ppe |' in text and '| msac |' in text
    assert (tmp_path / 'bench.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 'bench.png' in text
    if 'polylidar' in text:  # skipped with the reason unless installed
        assert 'polylidar skipped' in text or '| polylidar |' in text
    data = json.loads(raw.read_text())
    assert len(data['scans']) == 4 and 'sigma_20mm' in data['groups']


def test_eval_command_rejects_unknown_methods_and_levels(tiny_dataset, tmp_path, capsys):
    assert main(['eval', str(tiny_dataset), '--methods', 'magic', '--out', str(tmp_path / 'x.md'), '--quiet']) == 2
    assert 'unknown method' in capsys.readouterr().err
    assert main(['eval', str(tiny_dataset), '--noise', '5', '--out', str(tmp_path / 'x.md'), '--quiet']) == 2
    assert 'no noise level of 5 mm' in capsys.readouterr().err


def test_tune_command_writes_a_usable_params_file(tiny_dataset, tmp_path, capsys):
    out = tmp_path / 'tuned.yaml'
    assert (
        main(
            [
                'tune',
                str(tiny_dataset),
                '--noise',
                '20',
                '--lmax',
                '0.3',
                '0.6',
                '--sqrt-e',
                '0.1',
                '0.2',
                '-o',
                str(out),
                '--quiet',
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert 'best: lmax = ' in printed
    params = read_params_yaml(out)
    assert params['max_neighbor_distance'] in (0.3, 0.6)
    assert any(math.isclose(params['max_error_increment'], v) for v in (0.01, 0.04))
    assert main(['tune', str(tiny_dataset), '--noise', '20', '-o', str(out), '--quiet']) == 2  # no overwrite
    # the file drives `ppe eval`
    md = tmp_path / 'b.md'
    assert (
        main(
            [
                'eval',
                str(tiny_dataset),
                '--methods',
                'ppe',
                '--noise',
                '20',
                '--params',
                str(out),
                '--out',
                str(md),
                '--quiet',
                '--no-sweep',
            ]
        )
        == 0
    )
    assert f'lmax={params["max_neighbor_distance"]:g}' in md.read_text()


def test_eval_reuses_unchanged_methods_from_a_raw_file(tiny_dataset, tmp_path, capsys, monkeypatch):
    raw = tmp_path / 'raw.json'
    first = tmp_path / 'first.md'
    assert (
        main(
            [
                'eval',
                str(tiny_dataset),
                '--methods',
                'ppe',
                'msac',
                '--noise',
                '0',
                '--out',
                str(first),
                '--raw',
                str(raw),
                '--quiet',
                '--no-sweep',
            ]
        )
        == 0
    )
    from ppe_ros.benchmark.methods import MsacMethod as Msac

    def fail(self, points, origins=None):
        raise AssertionError('msac must not run again')

    monkeypatch.setattr(Msac, 'segment', fail)
    second = tmp_path / 'second.md'
    assert (
        main(
            [
                'eval',
                str(tiny_dataset),
                '--methods',
                'ppe',
                'msac',
                '--noise',
                '0',
                '--out',
                str(second),
                '--reuse',
                str(raw),
                '--lmax',
                '0.4',
                '--quiet',
                '--no-sweep',
            ]
        )
        == 0
    )
    msac_rows = [
        [line for line in path.read_text().splitlines() if line.startswith('| msac |')] for path in (first, second)
    ]
    assert msac_rows[0] == msac_rows[1] and len(msac_rows[0]) == 1
    text = second.read_text()
    assert 'taken from the earlier run' in text and '--reuse' in text and 'lmax=0.4' in text
    capsys.readouterr()


def test_eval_per_level_params_and_kept_hand_written_part(tiny_dataset, tmp_path, capsys):
    coarse = tmp_path / 'coarse.yaml'
    write_params_yaml(coarse, 0.001, 0.01)  # lmax 1 mm: finds no plane
    fine = tmp_path / 'fine.yaml'
    write_params_yaml(fine, 0.5, 0.01)
    out = tmp_path / 'bench.md'
    out.write_text('old report\n' + REPORT_END + '\n\n## Speed\n\nhand-written\n')
    raw = tmp_path / 'raw.json'
    assert (
        main(
            [
                'eval',
                str(tiny_dataset),
                '--methods',
                'ppe',
                'ppe-paper',
                '--params',
                str(coarse),
                f'20={fine}',
                '--out',
                str(out),
                '--raw',
                str(raw),
                '--quiet',
                '--no-sweep',
            ]
        )
        == 0
    )
    text = out.read_text()
    assert 'old report' not in text and text.count(REPORT_END) == 1
    assert text.endswith(REPORT_END + '\n\n## Speed\n\nhand-written\n')  # the part after the marker is kept
    assert f'--params {coarse} 20={fine}' in text and 'at 20 mm={lmax=0.5' in text and '| ppe-paper |' in text
    data = json.loads(raw.read_text())
    ppe = {g: {r['method']: r for r in v['rows']} for g, v in data['groups'].items()}
    assert ppe['sigma_0mm']['ppe']['f'] == 0.0  # the plain file: lmax 1 mm
    assert ppe['sigma_20mm']['ppe']['f'] > 0.0  # the 20 mm file
    capsys.readouterr()
    for bad in (['a.yaml', 'b.yaml'], ['x=a.yaml'], ['20=']):
        assert (
            main(['eval', str(tiny_dataset), '--methods', 'ppe', '--params', *bad, '--out', str(out), '--quiet']) == 2
        )
    assert '--params' in capsys.readouterr().err


@pytest.mark.parametrize('command', [['eval'], ['tune'], ['dataset', 'make'], ['score']])
def test_help_texts_print_plain_percent_signs(command, capsys):
    with pytest.raises(SystemExit):
        main([*command, '--help'])
    text = capsys.readouterr().out
    assert '%%' not in text and 'usage:' in text


def test_eval_progress_bar_counts_only_the_methods_that_run(tiny_dataset, tmp_path, capsys, monkeypatch):
    import ppe_ros.benchmark.peers as peers

    def missing(self):
        raise MethodUnavailable('polylidar is not installed')

    monkeypatch.setattr(peers.Polylidar3dOrganized, 'check_available', missing)
    assert (
        main(
            [
                'eval',
                str(tiny_dataset),
                '--methods',
                'msac',
                'polylidar',
                '--noise',
                '0',
                '--out',
                str(tmp_path / 'b.md'),
                '--no-sweep',
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert 'skipped polylidar' in err and '2/2 ' in err and '100%' in err  # 2 scans x msac; polylidar never runs


def test_bench_extraction_node_rows_use_the_settings_the_node_runs_with():
    """The node's e / lmax parameters default to 0 (= its sensor profile's): the benchmark's node rows must
    use the profile's values, not the literal 0 (which extract_plane_hierarchy rejects)."""
    import importlib.util
    from pathlib import Path

    from ppe_ros.core.sensor import PROFILES
    from ppe_ros.ros.processing import PARAM_SPEC_BY_NAME

    path = Path(__file__).resolve().parents[1] / 'benchmarks' / 'bench_extraction.py'
    spec = importlib.util.spec_from_file_location('bench_extraction_under_test', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    profile = PROFILES[PARAM_SPEC_BY_NAME['sensor'].default]
    assert module.NODE_E == profile.max_error_increment > 0
    assert module.NODE_LMAX == profile.max_neighbor_distance > 0


def test_bench_node_overhead_runs_on_the_ouster_sweep_with_the_nodes_settings(shared_data, capsys, monkeypatch):
    """bench_node_overhead --cloud ouster finds the planes with the node's own settings (whose e / lmax /
    min_plane_points of 0 mean the profile's: passing them to extract_planes as they are is an error) and
    prints its table."""
    import importlib.util
    from pathlib import Path

    benchmarks = Path(__file__).resolve().parents[1] / 'benchmarks'
    monkeypatch.syspath_prepend(str(benchmarks))
    monkeypatch.setenv('PPE_SHARED_DATA', str(shared_data))
    spec = importlib.util.spec_from_file_location(
        'bench_node_overhead_under_test', benchmarks / 'bench_node_overhead.py'
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(['--cloud', 'ouster', '--repeats', '1']) == 0
    out = capsys.readouterr().out
    assert 'planes from the node (sensor none)' in out and '| **total overhead** |' in out
