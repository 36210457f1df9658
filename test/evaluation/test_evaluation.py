"""Evaluation protocol: folds, selection, sweep, and the quick CLI run end to end, on generated
SocNav1-format data."""
import csv
import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from stars_ros.evaluation import executors, report
from stars_ros.model.config import ExperimentConfig
from stars_ros.errors import ConfigError
from stars_ros.evaluation.folds import grouped_folds, make_folds, sweep_samples
from stars_ros.evaluation.protocol import ProtocolConfig, run_protocol
from stars_ros.evaluation.summaries import paired_tests, time_accounting

REPO = Path(__file__).resolve().parents[2]


def _check_partition(folds, rows):
    tests = np.concatenate([f.test for f in folds])
    assert np.array_equal(np.sort(tests), np.sort(rows))  # every row tested exactly once
    for fold in folds:
        assert np.intersect1d(fold.train, fold.test).size == 0
        assert np.array_equal(np.sort(np.concatenate([fold.train, fold.test])), np.sort(rows))


def test_rows_protocol_keeps_an_examples_actions_together(synthetic):
    """Multi-action data: the rows protocol deals examples (user, scene), not ratings."""
    data = dataclasses.replace(synthetic, actions=np.arange(len(synthetic)) % 3,
                               users=np.repeat(synthetic.users[::3], 3)[:len(synthetic)],
                               scenes=np.repeat(synthetic.scenes[::3], 3)[:len(synthetic)],
                               action_names=('a', 'b', 'c'))
    examples = data.examples
    assert len(np.unique(examples)) == len(range(0, len(synthetic), 3))
    folds = make_folds(data, 'rows', 5, seed=0)
    _check_partition(folds, np.arange(len(data)))
    for fold in folds:
        assert not set(examples[fold.train].tolist()) & set(examples[fold.test].tolist())
        for part in make_folds(data, 'rows', 2, seed=[0, 1], rows=fold.train):
            assert not set(examples[part.train].tolist()) & set(examples[part.test].tolist())
        samples = sweep_samples(fold.train, [0.3, 1.0], [0, 2], examples)
        kept = set(examples[samples[0.3]].tolist())
        assert np.isin(examples[fold.train], list(kept)).sum() == len(samples[0.3])  # whole examples
    assert [f.test.tolist() for f in make_folds(data, 'rows', 5, seed=1)] != [f.test.tolist() for f in folds]


def test_grouped_folds_keep_groups_together_and_balance_sizes():
    groups = np.array(['a'] * 50 + ['b'] * 30 + ['c'] * 10 + ['d'] * 10 + ['e'] * 5)
    rows = np.arange(len(groups))
    folds = grouped_folds(rows, groups, 3, seed=0)
    _check_partition(folds, rows)
    for fold in folds:
        assert not set(groups[fold.train]) & set(groups[fold.test])
    # largest first to the emptiest fold: {a}, {b}, {c, d, e}
    assert sorted(len(f.test) for f in folds) == [25, 30, 50]
    with pytest.raises(ValueError):
        grouped_folds(rows, groups, 6, seed=0)


def test_grouped_folds_of_groups_of_distinct_sizes_are_the_same_under_every_seed():
    """The seed only orders groups of equal size (SocNav1's annotators all differ in size, so
    its cold-user folds do not change with the fold seed); equal sizes do move."""
    distinct = np.repeat(np.array(list('abcdefg')), [40, 35, 30, 20, 12, 7, 3])
    rows = np.arange(len(distinct))
    first = [fold.test.tolist() for fold in grouped_folds(rows, distinct, 3, seed=0)]
    assert all([fold.test.tolist() for fold in grouped_folds(rows, distinct, 3, seed=seed)] == first
               for seed in range(1, 50))
    equal = np.repeat(np.array(list('abcdef')), 10)
    assert len({str([f.test.tolist() for f in grouped_folds(rows[:60], equal, 3, seed=seed)])
                for seed in range(20)}) > 1


def test_shuffled_grouped_folds_move_with_the_seed_and_keep_groups_whole():
    distinct = np.repeat(np.array(list('abcdefg')), [40, 35, 30, 20, 12, 7, 3])
    rows = np.arange(len(distinct))
    dealt = {str([fold.test.tolist() for fold in grouped_folds(rows, distinct, 3, seed, deal='shuffled')])
             for seed in range(20)}
    assert len(dealt) > 5
    for fold in grouped_folds(rows, distinct, 3, 7, deal='shuffled'):
        assert not set(distinct[fold.test]) & set(distinct[fold.train])
        assert sorted(np.concatenate([fold.train, fold.test]).tolist()) == rows.tolist()
    with pytest.raises(ValueError, match='deal must be one of'):
        grouped_folds(rows, distinct, 3, 0, deal='alphabetical')


@pytest.mark.parametrize('protocol, key', [('cold-scene', 'scenes'), ('cold-user', 'users')])
def test_cold_folds_never_share_a_group(synthetic, protocol, key):
    groups = getattr(synthetic, key)
    folds = make_folds(synthetic, protocol, 5, seed=0)
    _check_partition(folds, np.arange(len(synthetic)))
    for fold in folds:
        assert not set(groups[fold.train].tolist()) & set(groups[fold.test].tolist())
        inner = make_folds(synthetic, protocol, 2, seed=[0, 1], rows=fold.train)
        _check_partition(inner, fold.train)
        for part in inner:
            assert not set(groups[part.train].tolist()) & set(groups[part.test].tolist())
    if protocol == 'cold-user':
        assert {len(set(synthetic.users[f.test].tolist())) for f in folds} <= {1, 2, 3, 4}


def test_rows_protocol_shares_scenes_between_train_and_test(synthetic):
    fold = make_folds(synthetic, 'rows', 5, seed=0)[0]
    assert set(synthetic.scenes[fold.train].tolist()) & set(synthetic.scenes[fold.test].tolist())
    with pytest.raises(ValueError, match='cold-user'):
        make_folds(synthetic, 'cold-users', 5, seed=0)


def test_sweep_samples_are_nested_without_replacement():
    pool = np.arange(100, 300)
    samples = sweep_samples(pool, [0.1, 0.5, 1.0], seed=[0, 0, 2])
    assert [len(samples[f]) for f in (0.1, 0.5, 1.0)] == [20, 100, 200]
    assert len(np.unique(samples[0.5])) == 100
    assert set(samples[0.1]) <= set(samples[0.5]) <= set(samples[1.0])
    assert np.array_equal(samples[1.0], pool)


def test_protocol_config_refuses_mistakes():
    with pytest.raises(ConfigError, match='^fold: unknown key'):
        ProtocolConfig.from_dict({'fold': 5})
    with pytest.raises(ConfigError, match=r'^grid\[0\]\[1\]: item missing$'):
        ProtocolConfig.from_dict({'grid': [[10]]})
    with pytest.raises(ConfigError, match=r"^sweep_backbones\[0\]: 'gat' is not among backbones"):
        ProtocolConfig.from_dict({'backbones': {'gcn': {}}, 'sweep_backbones': ['gat']})
    with pytest.raises(ConfigError, match=r'^backbones\.gcn\.hiden: unknown key'):
        ProtocolConfig.from_dict({'backbones': {'gcn': {'hiden': 3}}})
    with pytest.raises(ConfigError, match=r'^experiment\.training\.lr: Input should be greater than 0'):
        ProtocolConfig.from_dict({'experiment': {'training': {'lr': -1}}})


def test_shipped_configs_parse_and_quick_merges():
    full = ProtocolConfig.from_yaml(REPO / 'config' / 'eval_socnav1.yaml')
    assert full.folds == 5 and full.grid == ((10, 100), (50, 100), (100, 100))
    assert list(full.backbones) == ['gcn', 'gin', 'graphsage', 'ggnn', 'rgcn', 'gat']
    quick = ProtocolConfig.from_yaml(REPO / 'config' / 'eval_socnav1.yaml', REPO / 'config' / 'eval_quick.yaml')
    assert quick.folds == 2 and quick.backbones == full.backbones
    gat = quick.experiment_config('gat', 'stars')
    assert (gat.encoder.name, gat.encoder.hidden, gat.encoder.options) == ('gat', 16, {'heads': 4})


def test_selection_takes_the_lowest_inner_error_and_retrains_with_it(synthetic, monkeypatch):
    """A fake fit whose inner error is lowest for (50, 100) only under StARS, and, within
    the search space, for lr 1e-3 under base and embedding_l2 0.1 under StARS; inner fits
    sharing a start T1 are one fit scored along the way."""
    seen = []

    def fake_fit(task, data=None):
        training = task.experiment['training']
        pair = (training['pretrain_epochs'], training['joint_epochs'])
        seen.append((task.model, task.stage, pair, len(task.train), task.fraction, task.curve_at))
        variant = task.experiment['model']['variant']
        best = (50, 100) if variant == 'stars' else (10, 100)
        good = training['lr'] == 1e-3 if variant == 'base' else training['embedding_l2'] == 0.1

        def error(t1, t2):
            return (0.5 if (t1, t2) == best else 0.9) - (0.1 if good else 0.0) + 0.001 * (100 - t2)
        mse = 0.02 if variant == 'stars' else 0.03
        mse += 0.001 * len(task.test) / 1000
        return {'mse': mse, 'rmse': mse ** 0.5, 'pearson_r': 0.9, 'ccc': 0.9, 'n': len(task.test),
                'z_rmse': error(*pair), 'fit_seconds': 1.0, 'predict_seconds': 0.1, 'epochs': sum(pair),
                **({'curve': [{'epoch': t2, 'z_rmse': error(pair[0], t2)} for t2 in task.curve_at]}
                   if task.curve_at else {})}

    monkeypatch.setattr(executors, 'run_fit', fake_fit)
    config = ProtocolConfig.from_dict({'folds': 3, 'backbones': {'gcn': {}}, 'sweep_backbones': ['gcn'],
                                       'grid': [[10, 60], [10, 100], [50, 100], [100, 100]],
                                       'search': {'base': {'lr': [3e-4, 1e-3]}, 'stars': {'embedding_l2': [0.01, 0.1]}},
                                       'fractions': [0.5, 1.0], 'baselines': ['population_mean', 'mf']})
    result = run_protocol(synthetic, config, 'rows')
    final = {(r['model'], r['fold']): (r['T1'], r['T2'], json.dumps(r['settings'])) for r in result.final()}
    folds = ('0:0', '0:1', '0:2')
    assert {final['GCN StARS', f] for f in folds} == {(50, 100, '{"embedding_l2": 0.1}')}
    assert {final['GCN base', f] for f in folds} == {(10, 100, '{"lr": 0.001}')}
    assert {final['MF (biased, no content)', f] for f in folds} == {(0, 100, '{}')}
    inner = [s for s in seen if s[1] == 'inner']
    # folds × inner folds × (settings × starts) for base and StARS; T1 = 10 is one fit to T2 = 100
    assert len(inner) == 3 * 2 * (2 * 3 + 2 * 3) + 3 * 2 * 1  # mf: T2 60 or 100, one fit
    assert {s[5] for s in inner if s[2][0] == 10} == {(60, 100)}
    assert len([s for s in seen if s[1] == 'sweep']) == 3 * 3  # folds × (base, StARS, mf) at 0.5
    assert {r['model'] for r in result.records if r['fraction'] == 0.5} == {
        'Population mean', 'MF (biased, no content)', 'GCN base', 'GCN StARS'}
    assert len(result.choices) == 3 * 3 and all(c['fold'] in folds for c in result.choices)
    tests = paired_tests(result, ['mse', 'ccc'])
    mse = next(t for t in tests if t['metric'] == 'mse')
    assert mse['delta'] == pytest.approx(-0.01) and mse['p_holm'] == 0.0
    assert next(t for t in tests if t['metric'] == 'ccc')['p'] == 1.0
    timing = time_accounting(result)
    assert timing['by_stage']['inner'] == pytest.approx(len(inner) * 1.1)


def test_ablations_follow_the_stars_choice_of_each_fold(synthetic, monkeypatch):
    def fake_fit(task, data=None):
        training, model = task.experiment['training'], task.experiment['model']
        error = 0.4 if training['embedding_l2'] == 0.1 else 0.6
        mse = {'base': 0.04}.get(model['variant'], 0.03 if model['item_key'] == 'prefix' else 0.02)
        return {'mse': mse, 'rmse': 0.14, 'pearson_r': 0.9, 'ccc': 0.9, 'n': len(task.test), 'z_rmse': error,
                'fit_seconds': 1.0, 'predict_seconds': 0.1, 'epochs': 2,
                **({'curve': [{'epoch': t, 'z_rmse': error} for t in task.curve_at]} if task.curve_at else {})}

    monkeypatch.setattr(executors, 'run_fit', fake_fit)
    config = ProtocolConfig.from_dict({
        'folds': 2, 'grid': [[1, 2]], 'backbones': {'gcn': {}}, 'baselines': [],
        'search': {'stars': {'embedding_l2': [0.01, 0.1]}}, 'ablation_backbones': ['gcn'],
        'ablations': ['user_bias', 'stars_no_q', 'stars_prefix']})
    result = run_protocol(synthetic, config, 'rows')
    final = {r['model']: r for r in result.final()}
    assert set(final) == {'GCN base', 'GCN StARS', 'GCN user offsets only', 'GCN StARS without q_i',
                          'GCN StARS, items keyed by prefix'}
    for label in ('GCN user offsets only', 'GCN StARS without q_i', 'GCN StARS, items keyed by prefix'):
        assert final[label]['settings'] == {'embedding_l2': 0.1}
    assert final['GCN user offsets only']['variant'] == 'user_bias'
    assert report.comparison_table(result, 'mse', 'x')[2].startswith('| GCN | .040 → .020 |')  # not the prefix row
    assert not [s for s in result.inner if s['model'] not in ('GCN base', 'GCN StARS')]
    with pytest.raises(ConfigError, match=r'^ablations\[0\]: Input should be'):
        ProtocolConfig.from_dict({'ablations': ['stars_no_p']})
    with pytest.raises(ConfigError, match=r'^search\.stars\.hidden: not an allowed key'):
        ProtocolConfig.from_dict({'search': {'stars': {'hidden': [8]}}})
    with pytest.raises(ConfigError, match='T2 >= 1'):
        ProtocolConfig.from_dict({'grid': [[10, 0]]})


def test_the_point_estimate_ablation_is_the_stars_choice_with_the_posterior_head_off(synthetic, monkeypatch):
    def fake_fit(task, data=None):
        training = task.experiment['training']
        error = 0.4 if training['posterior_sweeps'] else 0.6
        mse = 0.01 if training['posterior_sweeps'] else 0.03  # tells which model was fitted
        return {'mse': mse, 'rmse': 0.14, 'pearson_r': 0.9, 'ccc': 0.9, 'n': len(task.test), 'z_rmse': error,
                'fit_seconds': 1.0, 'predict_seconds': 0.1, 'epochs': 2,
                **({'curve': [{'epoch': t, 'z_rmse': error} for t in task.curve_at]} if task.curve_at else {})}

    monkeypatch.setattr(executors, 'run_fit', fake_fit)
    config = ProtocolConfig.from_dict({
        'folds': 2, 'grid': [[1, 3]], 'backbones': {'gcn': {}}, 'baselines': [],
        'search': {'stars': {'embedding_l2': [0.01, 0.1], 'posterior_sweeps': [0, 2]}},
        'experiment': {'training': {'posterior_burn_in': 1}},
        'ablation_backbones': ['gcn'], 'ablations': ['stars_point']})
    final = {r['model']: r for r in run_protocol(synthetic, config, 'rows').final()}
    chosen = final['GCN StARS']
    assert chosen['settings']['posterior_sweeps'] == 2 and chosen['mse'] == 0.01
    point = final['GCN StARS, trained point estimate (no posterior head)']
    assert point['settings'] == chosen['settings'] and point['mse'] == 0.03  # its own setting wins over the choice


@pytest.mark.slow
def test_quick_cli_end_to_end(synthetic_root, tmp_path):
    out = tmp_path / 'quick'
    env = {**os.environ, 'PYTHONPATH': str(REPO)}
    done = subprocess.run(
        [sys.executable, '-m', 'offline_training.evaluate', '--quick', '--backbones', 'gcn,gat', '--jobs', '1',
         '--data-root', str(synthetic_root), '--protocol', 'cold-scene', '--out', str(out)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads((out / 'results.json').read_text())
    assert results['protocol'] == 'cold-scene' and len(results['folds']) == 2
    models = {'Population mean', 'MF (biased, no content)', 'GCN base', 'GCN StARS', 'GAT base', 'GAT StARS'}
    final = [r for r in results['records'] if r['fraction'] == 1.0]
    assert {r['model'] for r in final} == models and len(final) == 2 * len(models)
    assert all(0 < r['mse'] < 0.3 for r in final)
    assert {(t['backbone'], t['metric']) for t in results['tests']} == {
        (b, m) for b in ('gcn', 'gat') for m in ('mse', 'pearson_r', 'ccc')}
    with (out / 'folds.csv').open() as handle:
        assert len(list(csv.DictReader(handle))) == len(results['records'])
    tables = (out / 'tables.md').read_text()
    for heading in ('| Model | MSE | r | CCC |', '| Backbone | ΔMSE | t(1) | Holm p', 'MSE base → StARS',
                    '## Sparsity', '## Where the time goes'):
        assert heading in tables
    for metric in ('mse', 'pearson_r', 'ccc'):
        assert (out / f'sparsity_{metric}.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 'offline_training.evaluate' in (out / 'command.txt').read_text()
    assert len((out / 'records.jsonl').read_text().splitlines()) == len(results['records']) + len(results['inner'])


def test_device_option_reaches_every_fit_and_the_results(synthetic_root, tmp_path, monkeypatch):
    """``--device`` overrides the config for every fit (a fake fit: no GPU needed) and is
    recorded in config.yaml, machine.json and tables.md."""
    from offline_training import evaluate
    devices = []

    def fake_fit(task, data=None):
        devices.append(ExperimentConfig.from_dict(task.experiment).training.device)
        return {'mse': 0.02, 'rmse': 0.14, 'pearson_r': 0.9, 'ccc': 0.9, 'n': len(task.test), 'z_rmse': 0.5,
                'fit_seconds': 1.0, 'predict_seconds': 0.1, 'epochs': 2,
                'curve': [{'epoch': t, 'z_rmse': 0.5} for t in task.curve_at]}

    monkeypatch.setattr(executors, 'run_fit', fake_fit)
    out = tmp_path / 'device'
    assert evaluate.main(['--quick', '--backbones', 'gat', '--device', 'cuda:1', '--data-root', str(synthetic_root),
                          '--out', str(out)]) == 0
    assert devices and set(devices) == {'cuda:1'}
    written = yaml.safe_load((out / 'config.yaml').read_text())
    assert written['device'] == 'cuda:1' and written['experiment']['training']['device'] == 'cuda:1'
    assert json.loads((out / 'machine.json').read_text())['device'] == 'cuda:1'
    assert 'training on cuda:1' in (out / 'tables.md').read_text()
    assert evaluate.main(['--quick', '--device', 'gpu', '--data-root', str(synthetic_root), '--out', str(out)]) == 2


@pytest.mark.parametrize('program', ['evaluate', 'kshot'])
def test_a_run_from_uncommitted_changes_is_refused_unless_allowed(program, synthetic_root, tmp_path, monkeypatch,
                                                                  capsys):
    """A run that results cite starts from a commit: a dirty tree (its own --out folder not
    counted) refuses it before anything is written; --allow-dirty and --quick may run."""
    import importlib
    from stars_ros.evaluation import provenance
    command = importlib.import_module(f'offline_training.{program}')
    config = ['--config', 'config/socnav1_gat.yaml'] if program == 'kshot' else []
    asked = []

    def dirty(ignoring=None):
        asked.append(ignoring)
        return {'commit': 'abc', 'dirty': True}
    monkeypatch.setattr(provenance, 'git_state', dirty)
    out = tmp_path / 'dirty'
    assert command.main([*config, '--data-root', str(synthetic_root), '--out', str(out)]) == 2
    assert 'have uncommitted changes' in capsys.readouterr().err and not out.exists()
    assert asked == [out]
    missing = tmp_path / 'no data'  # past the check, the next refusal is the data's
    for allowed in (['--allow-dirty'], ['--quick']):
        assert command.main([*config, *allowed, '--data-root', str(missing), '--out', str(out)]) == 2
        error = capsys.readouterr().err
        assert 'have uncommitted changes' not in error and 'no such data folder' in error


def test_resume_runs_only_the_fits_an_earlier_run_did_not_finish(synthetic_root, tmp_path, monkeypatch):
    """A run stopped after some fits (records.jsonl cut short), resumed: only the missing
    fits run, and the results equal an uninterrupted run's."""
    from offline_training import evaluate
    ran = []

    def fake_fit(task, data=None):
        training = task.experiment['training']
        pair = (training['pretrain_epochs'], training['joint_epochs'])
        ran.append((task.model, task.fold, task.stage, task.fraction, task.inner_fold, pair))
        score = (sum(pair) * 7 + len(task.train) + 3 * task.inner_fold) % 11 / 100 + 0.01
        return {'mse': score, 'rmse': score ** 0.5, 'pearson_r': 0.9, 'ccc': 0.8, 'n': len(task.test),
                'z_rmse': score, 'fit_seconds': 1.0, 'predict_seconds': 0.1, 'epochs': sum(pair),
                'curve': [{'epoch': t, 'z_rmse': score + t / 1000} for t in task.curve_at]}

    monkeypatch.setattr(executors, 'run_fit', fake_fit)
    args = ['--quick', '--backbones', 'gat', '--data-root', str(synthetic_root)]
    whole, part = tmp_path / 'whole', tmp_path / 'part'
    run_record = evaluate.run_record

    def made_at(commit, dirty):
        monkeypatch.setattr(evaluate, 'run_record', lambda argv, device=None: {
            **run_record(argv, device), 'git': {'commit': commit, 'dirty': dirty}})
    made_at('first', False)
    assert evaluate.main([*args, '--out', str(whole)]) == 0
    all_fits = list(ran)
    lines = (whole / 'records.jsonl').read_text().splitlines()
    assert len(lines) == len(json.loads((whole / 'results.json').read_text())['records']) + \
        sum(1 for fit in all_fits if fit[2] == 'inner')
    part.mkdir()
    (part / 'config.yaml').write_text((whole / 'config.yaml').read_text())
    kept = lines[:len(lines) // 2]
    (part / 'records.jsonl').write_text('\n'.join(kept) + '\n{"model": "cut sho')
    ran.clear()
    made_at('second', True)
    assert evaluate.main([*args, '--out', str(part), '--resume', '--jobs', '1']) == 0
    reused = sum(1 for line in kept if json.loads(line).get('variant') != 'population_mean')  # recomputed
    assert 0 < reused and len(ran) == len(all_fits) - reused and set(ran) <= set(all_fits)

    def results(folder):  # the population mean's fit time is measured; NaN (its r) != NaN
        values = json.loads((folder / 'results.json').read_text())
        return json.dumps([[{k: v for k, v in entry.items() if k not in ('fit_seconds', 'fitted_by')}
                            for entry in values[name]] for name in ('records', 'inner', 'selection', 'tests')])
    assert results(part) == results(whole)
    first = {'commit': 'first', 'dirty': False, 'device': 'cpu'}
    second = {'commit': 'second', 'dirty': True, 'device': 'cpu'}
    whole_lines = [json.loads(line) for line in (whole / 'records.jsonl').read_text().splitlines()]
    assert {json.dumps(entry['fitted_by']) for entry in whole_lines} == {json.dumps(first)}
    stamps = {}
    for line in (part / 'records.jsonl').read_text().splitlines():  # each fit says which process made it
        entry = json.loads(line)
        stamps.setdefault(entry['variant'] == 'population_mean' or json.dumps(entry['fitted_by']), 0)
    assert set(stamps) == {True, json.dumps(first), json.dumps(second)}
    assert f'{reused} fits came from the earlier run' in (part / 'tables.md').read_text()
    assert evaluate.main([*args, '--out', str(part), '--resume', '--device', 'cuda']) == 2  # other settings


def test_failed_fits_are_named_and_stop_only_what_needs_them(synthetic, monkeypatch):
    """An inner fit that raises leaves its fold without a choice (so without the final fits
    of StARS and of the ablation following it); a final fit that raises is missing alone; a
    fit that diverges is a result, recorded with its error. Everything else completes."""
    def fake_fit(task, data=None):
        if (task.model, task.fold, task.stage, task.inner_fold) in {('GCN StARS', '0:1', 'inner', 0),
                                                                    ('GCN base', '0:0', 'final', -1)}:
            raise RuntimeError('injected')
        diverged = (task.model, task.fold) == ('GCN base', '0:1')
        return {'mse': math.nan if diverged else 0.02, 'rmse': 0.14, 'pearson_r': 0.9, 'ccc': 0.9,
                'n': len(task.test), 'z_rmse': 0.5, 'fit_seconds': 1.0, 'predict_seconds': 0.1, 'epochs': 2,
                **({'error': 'training diverged'} if diverged else {}),
                **({'curve': [{'epoch': t, 'z_rmse': 0.5} for t in task.curve_at]} if task.curve_at else {})}

    monkeypatch.setattr(executors, 'run_fit', fake_fit)
    config = ProtocolConfig.from_dict({'folds': 2, 'grid': [[1, 1], [0, 2]], 'backbones': {'gcn': {}},
                                       'baselines': ['population_mean'], 'ablation_backbones': ['gcn'],
                                       'ablations': ['user_bias']})
    result = run_protocol(synthetic, config, 'rows')
    assert [(f['fit'], f['error']) for f in result.failed] == [
        ('GCN base fold 0:0 final (T1, T2) = (1, 1)', 'RuntimeError: injected'),
        ('GCN StARS fold 0:1 inner fold 0 (T1, T2) = (1, 1)', 'RuntimeError: injected'),
        ('GCN StARS fold 0:1 inner fold 0 (T1, T2) = (0, 2)', 'RuntimeError: injected')]
    assert result.unchosen == [{'model': 'GCN StARS', 'fold': '0:1'}]
    models = ('Population mean', 'GCN base', 'GCN StARS', 'GCN user offsets only')
    missing = {('GCN base', '0:0'), ('GCN StARS', '0:1'), ('GCN user offsets only', '0:1')}
    assert sorted((r['model'], r['fold']) for r in result.final()) == sorted(
        {(m, f) for m in models for f in ('0:0', '0:1')} - missing)
    diverged, = (r for r in result.records if 'error' in r)
    assert (diverged['model'], diverged['fold'], diverged['error']) == ('GCN base', '0:1', 'training diverged')
    assert not [e for e in result.inner if (e['model'], e['fold'], e['inner_fold']) == ('GCN StARS', '0:1', 0)]


def test_a_run_with_failed_fits_ends_without_tables_and_resume_runs_them(synthetic_root, tmp_path, monkeypatch,
                                                                           capsys):
    """A run over a finished one, in which an inner fit raises: status 1, the fit named,
    the earlier tables removed, no new ones. --resume runs that fit and the final fits its
    selection unlocks, nothing else, and ends with the first run's results."""
    from offline_training import evaluate
    ran, broken = [], set()

    def fake_fit(task, data=None):
        if (task.model, task.fold, task.stage, task.inner_fold) in broken:
            raise RuntimeError('injected')
        training = task.experiment['training']
        ran.append((task.model, task.fold, task.stage, task.fraction, task.inner_fold))
        score = (training['pretrain_epochs'] * 7 + len(task.train) + 3 * task.inner_fold) % 11 / 100 + 0.01
        return {'mse': score, 'rmse': score ** 0.5, 'pearson_r': 0.9, 'ccc': 0.8, 'n': len(task.test),
                'z_rmse': score, 'fit_seconds': 1.0, 'predict_seconds': 0.1, 'epochs': 2,
                'curve': [{'epoch': t, 'z_rmse': score + t / 1000} for t in task.curve_at]}

    monkeypatch.setattr(executors, 'run_fit', fake_fit)
    out = tmp_path / 'out'
    args = ['--quick', '--backbones', 'gat', '--data-root', str(synthetic_root), '--out', str(out)]
    assert evaluate.main(args) == 0
    whole = (out / 'results.json').read_text()
    broken.add(('GAT StARS', '0:1', 'inner', 1))
    assert evaluate.main(args) == 1
    stderr = capsys.readouterr().err
    assert 'GAT StARS fold 0:1 inner fold 1 (T1, T2) = (1, 1): RuntimeError: injected' in stderr
    assert 'GAT StARS fold 0:1: no settings chosen (an inner fit failed)' in stderr and 'No tables' in stderr
    assert not (out / 'tables.md').exists() and not (out / 'results.json').exists()
    assert [json.loads(line)['fit'] for line in (out / 'failed.jsonl').read_text().splitlines()] == [
        'GAT StARS fold 0:1 inner fold 1 (T1, T2) = (1, 1)', 'GAT StARS fold 0:1 inner fold 1 (T1, T2) = (0, 2)']
    assert not [line for line in (out / 'records.jsonl').read_text().splitlines()
                if '"GAT StARS"' in line and '"0:1"' in line and '"inner_fold": 1' in line]
    broken.clear()
    ran.clear()
    assert evaluate.main([*args, '--resume']) == 0
    assert sorted(ran) == [('GAT StARS', '0:1', 'final', 1.0, -1), ('GAT StARS', '0:1', 'inner', 1.0, 1),
                           ('GAT StARS', '0:1', 'inner', 1.0, 1), ('GAT StARS', '0:1', 'sweep', 0.5, -1)]
    assert not (out / 'failed.jsonl').exists()

    def results(text):  # in any order; the population mean's fit time is measured anew
        values = json.loads(text)
        return {name: sorted(json.dumps({k: v for k, v in entry.items() if k != 'fit_seconds'}, sort_keys=True)
                             for entry in values[name]) for name in ('records', 'inner', 'selection', 'tests')}
    assert results((out / 'results.json').read_text()) == results(whole)
