"""k-shot evaluation: folds and pools are sound, and the quick run writes every output."""
import json

import numpy as np
import pytest

from offline_training import kshot
from stars_ros.evaluation.kshot import annotator_folds, reveal_pools


def test_annotator_folds_and_pools_partition_the_data(socnav1):
    folds = annotator_folds(socnav1.users, 3, seed=0)
    names = sorted(set(socnav1.users.tolist()))
    assert sorted(n for fold in folds for n in fold) == names and [len(f) for f in folds] == [4, 4, 4]
    assert folds == annotator_folds(socnav1.users, 3, seed=0) != annotator_folds(socnav1.users, 3, seed=1)
    pools = reveal_pools(socnav1, folds[0], 20, seed=0)
    for name, (revealed, test) in pools.items():
        rows = np.flatnonzero(socnav1.users == name)
        assert len(revealed) == 20 and not set(revealed) & set(test)
        assert sorted(np.concatenate([revealed, test])) == sorted(rows)


def test_quick_run_writes_tables_plot_and_comparable_curves(socnav1_root, tmp_path, capsys):
    out = tmp_path / 'kshot'
    assert kshot.main(['--config', 'config/socnav1_gat.yaml', '--data-root', str(socnav1_root), '--out', str(out),
                       '--quick']) == 0
    assert {'results.json', 'results.md', 'kshot.png'} <= {p.name for p in out.iterdir()}
    results = json.loads((out / 'results.json').read_text())
    assert results['complete'] and results['ks'] == [0, 2, 5] and len(results['folds']['0']) == 2
    for fold in (0, 1):
        records = [r for r in results['records'] if r['fold'] == fold]
        assert len({r['n_test'] for r in records}) == 1  # the same test rows for every k
        zero = records[0]
        assert zero['k'] == 0
        assert abs(zero['fold-in (zero prior)']['mse'] - zero['unpersonalised']['mse']) < 1e-9
        assert abs(zero['retrained']['mse'] - zero['unpersonalised']['mse']) < 1e-6  # k = 0 is the fold's model
        assert len({json.dumps(r['unpersonalised']) for r in records}) == 1
    assert set(results['regularisation']['0']) == {'fold-in', 'fold-in (zero prior)'}
    assert '| 5 | retrained |' in (out / 'results.md').read_text()
    assert 'of the k=0 -> full retraining MSE gap' in capsys.readouterr().out


@pytest.mark.slow
def test_fits_in_worker_processes_give_what_inline_fits_give(socnav1_root, tmp_path):
    """Two seeds' folds with their fits in 2 worker processes, then all inline: same records."""
    runs = {}
    for jobs in (2, 1):
        out = tmp_path / f'jobs{jobs}'
        assert kshot.main(['--config', 'config/socnav1_gat.yaml', '--data-root', str(socnav1_root), '--out', str(out),
                           '--quick', '--seeds', '0', '1', '--jobs', str(jobs)]) == 0
        runs[jobs] = json.loads((out / 'results.json').read_text())
    assert set(runs[2]['folds']) == {'0', '1'}
    assert [(r['seed'], r['fold'], r['k']) for r in runs[2]['records']] == \
        [(seed, fold, k) for seed in (0, 1) for fold in (0, 1) for k in (0, 2, 5)]  # --quick's ks
    for parallel, inline in zip(runs[2]['records'], runs[1]['records']):
        assert parallel['retrained'] == inline['retrained'] and parallel['fold-in'] == inline['fold-in']
    assert runs[2]['jobs'] == 2 and runs[2]['seeds'] == [0, 1]


def test_a_fold_whose_fit_fails_is_left_out_and_named(socnav1_root, tmp_path, monkeypatch, capsys):
    """The fourth fit (fold 1's retraining at k = 5, the largest first) raises: fold 0 is
    reported, fold 1 is named with the error and left out, and the run ends with status 1."""
    calls, fit_rows = [], kshot.fit_rows

    def failing_fourth(*args, **kwargs):
        calls.append(args)
        if len(calls) == 4:
            raise RuntimeError('injected')
        return fit_rows(*args, **kwargs)

    monkeypatch.setattr(kshot, 'fit_rows', failing_fourth)
    out = tmp_path / 'kshot'
    assert kshot.main(['--config', 'config/socnav1_gat.yaml', '--data-root', str(socnav1_root), '--out', str(out),
                       '--quick']) == 1
    results = json.loads((out / 'results.json').read_text())
    assert not results['complete'] and {r['fold'] for r in results['records']} == {0}
    assert results['failed'] == [{'seed': 0, 'fold': 1, 'k': 5, 'error': 'RuntimeError: injected'}]
    assert 'seed 0 fold 1 k=5: RuntimeError: injected' in capsys.readouterr().err
