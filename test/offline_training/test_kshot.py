"""k-shot evaluation on the generated SocNav1-format data: folds and pools are dealt by example,
people too small for a pool are left out and counted, the strategies ask only pool examples,
and the quick run writes every output with comparable curves and its calibration."""
import json

import numpy as np
import pytest
import yaml

from offline_training import kshot
from stars_ros.evaluation import kshot_report, kshot_run
from stars_ros.evaluation.kshot import (EXACT_SETS, STRATEGIES, Design, Person, annotator_folds, coverage, known_split,
                                       random_sets, reveal_pools)
from stars_ros import StarsRecommender
from conftest import TINY_CONFIG


def test_pools_are_whole_examples_and_small_people_are_left_out(synthetic):
    folds = annotator_folds(synthetic.users, 3, seed=0)
    assert sorted(n for fold in folds for n in fold) == sorted(set(synthetic.users.tolist()))
    assert folds == annotator_folds(synthetic.users, 3, seed=0) != annotator_folds(synthetic.users, 3, seed=1)
    examples = synthetic.examples
    people, left_out = reveal_pools(synthetic, sorted(set(synthetic.users.tolist())), 20, seed=0)
    for name, person in people.items():
        rows = np.flatnonzero(synthetic.users == name)
        count = len(np.unique(examples[rows]))
        assert len(person.pool) == min(20, count - 1)
        assert all(len(np.unique(examples[rows_of])) == 1 for rows_of in person.pool)  # one example each
        pooled = person.rows(range(len(person.pool)))
        assert not set(pooled) & set(person.test)
        assert sorted(np.concatenate([pooled, person.test])) == sorted(rows)
        assert not set(examples[pooled]) & set(examples[person.test])  # an example is never split
    assert all(count == 1 for count in left_out.values())


def test_the_known_split_holds_out_whole_examples(synthetic):
    rows = np.arange(len(synthetic))
    train, held = known_split(synthetic, rows, 0.25, seed=0)
    assert sorted(np.concatenate([train, held])) == list(rows)
    assert not set(synthetic.examples[train]) & set(synthetic.examples[held])


@pytest.fixture(scope='module')
def design(synthetic):
    return Design(StarsRecommender(TINY_CONFIG).fit(synthetic).fitted, synthetic)


def test_strategies_ask_only_pool_examples_each_once(design, synthetic):
    people, _ = reveal_pools(synthetic, ['a', 'b', 'c'], 8, seed=0)
    for person in people.values():
        for strategy in STRATEGIES:
            order = design.reveal_order(person, strategy, 6)
            assert len(order) == min(6, len(person.pool)) and len(set(order)) == len(order)
            assert set(order) <= set(range(len(person.pool)))
        assert design.reveal_order(person, 'random', 6) == list(range(min(6, len(person.pool))))


def test_random_answers_take_every_set_of_k_pool_examples_while_there_are_few_else_seeded_ones():
    person = Person(pool=tuple(np.array([e]) for e in range(20)), test=np.array([20]))
    assert random_sets(person, 'a', 1, 64, seed=0) == [[e] for e in range(20)]
    every = random_sets(person, 'a', 3, 64, seed=0)
    assert len(every) == 1140 == EXACT_SETS and every[0] == [0, 1, 2]
    assert len({tuple(chosen) for chosen in every}) == 1140 and all(len(set(chosen)) == 3 for chosen in every)
    drawn = random_sets(person, 'a', 5, 64, seed=0)  # C(20, 5) = 15504: too many to take whole
    assert len(drawn) == 64 and drawn[0] == [0, 1, 2, 3, 4]
    assert all(len(set(chosen)) == 5 and set(chosen) <= set(range(20)) for chosen in drawn)
    assert drawn == random_sets(person, 'a', 5, 64, seed=0) != random_sets(person, 'a', 5, 64, seed=1)
    assert random_sets(person, 'a', 20, 64, seed=0) == [list(range(20))]


def test_random_answers_score_the_mean_over_every_first_answer(design, synthetic):
    """k = 1: the fold's random MSE is the mean, over each pool example answered first, of the
    MSE of the posterior from that one answer (by hand, through ``Design``)."""
    held = ['a', 'b']
    people, left_out = reveal_pools(synthetic, held, 4, seed=0)
    fold = (0, 0, held, np.zeros(0, dtype=np.int64), people, left_out, np.zeros(0, dtype=np.int64))
    settings = kshot_run.KShotSettings(folds=2, seeds=(0,), pool=4, ks=(1,), strategies=('random',), retrain_ks=(0,),
                                       known_test=0.0, ridge_lambda=1.0, random_sets=64)
    records, _ = kshot_run.score_fold(settings, synthetic, design, fold, {})
    _, rows = kshot_run.test_rows(people, 1)
    by_hand = []
    for first in range(4):
        predictions = np.zeros(len(synthetic))
        for person in people.values():
            theta, _ = design.posterior(person.rows([first]))
            predictions[person.test] = design.predict(person.test, theta)
        by_hand.append(np.mean((predictions[rows] - synthetic.scores[rows]) ** 2))
    assert records[0]['fold-in (random)']['mse'] == pytest.approx(np.mean(by_hand), rel=1e-9)


def test_the_first_active_question_is_the_one_with_the_largest_expected_variance_reduction(design, synthetic):
    people, _ = reveal_pools(synthetic, ['b'], 8, seed=0)
    person = people['b']
    _, covariance = design.posterior(np.zeros(0, dtype=np.int64))
    blocks = [design.rows(rows) for rows in person.pool]
    targets = (np.concatenate([b[0] for b in blocks]), np.concatenate([b[3] for b in blocks]))
    gains = design.uncertainty.variance_reduction([(b[0], b[3]) for b in blocks], targets, covariance)
    assert design.reveal_order(person, 'active', 1) == [int(np.argmax(gains))]


def test_the_first_decision_question_is_the_one_with_the_largest_log_decision_value(design, synthetic):
    people, _ = reveal_pools(synthetic, ['b'], 8, seed=0)
    person = people['b']
    theta, covariance = design.posterior(np.zeros(0, dtype=np.int64))
    blocks = [design.rows(rows) for rows in person.pool]
    assert all(len(b[0]) == 1 for b in blocks)  # one action, as SocNav1: the pool's scenes are ranked as one set
    pooled = tuple(np.concatenate([b[part] for b in blocks]) for part in (0, 1, 3))
    values = design.uncertainty.log_decision_value([(b[0], b[3]) for b in blocks], [pooled], theta, covariance)
    assert np.isfinite(values).all() and len(set(values.tolist())) > 1  # clear choices still tell questions apart
    assert design.reveal_order(person, 'decision', 1) == [int(np.argmax(values))]


def test_first_choice_regret_is_the_best_true_score_less_that_of_the_predicted_best_by_hand():
    y = np.array([5.0, 3.0, 1.0, 4.0, 2.0, 3.0])
    p = np.array([1.0, 2.0, 0.0, 3.0, 9.0, 0.0])
    groups = np.array([0, 0, 0, 1, 1, 2])  # group 2 rates one action: no choice
    # group 0 picks row 1 (true 3, best 5): 2; group 1 picks row 4 (true 2, best 4): 2
    assert kshot_run.first_choice_regret(y, p, groups) == pytest.approx(2.0)
    assert kshot_run.first_choice_regret(y[:3], np.array([9.0, 0.0, 0.0]), groups[:3]) == 0.0
    assert kshot_run.first_choice_regret(y, p, np.arange(6)) is None


def test_coverage_counts_ratings_inside_the_central_intervals():
    y = np.array([0.0, 0.5, 1.0, 3.0])
    result = coverage(y, np.zeros(4), np.ones(4))  # |y| <= z: 50 % z = 0.674, 80 % 1.28, 90 % 1.64, 95 % 1.96
    assert result == {'0.5': 0.5, '0.8': 0.75, '0.9': 0.75, '0.95': 0.75}


@pytest.mark.parametrize('strangers', ['base_encoder', 'prior_mean'])
def test_quick_run_writes_tables_plot_calibration_and_comparable_curves(strangers, synthetic_root, tmp_path, capsys):
    """The packaged config ('base_encoder': the fold's model serves its new people the plain
    encoder, the one beside) and the same config serving strangers the prior's mean (the plain
    encoder fitted beside it)."""
    config = yaml.safe_load(open('config/socnav1_gat.yaml'))
    assert config['model']['strangers'] == 'base_encoder'
    config['model']['strangers'] = strangers
    (tmp_path / 'config.yaml').write_text(yaml.safe_dump(config))
    out = tmp_path / 'kshot'
    assert kshot.main(['--config', str(tmp_path / 'config.yaml'), '--data-root', str(synthetic_root), '--out', str(out),
                       '--quick', '--strategies', 'random', 'active']) == 0
    assert {'results.json', 'results.md', 'kshot.png'} <= {p.name for p in out.iterdir()}
    results = json.loads((out / 'results.json').read_text())
    assert results['complete'] and results['ks'] == [0, 1, 2, 5] and len(results['folds']['0']) == 2
    assert set(results['git']) == {'commit', 'dirty'} and results['machine']['device'] == 'cpu'
    for fold in (0, 1):
        records = [r for r in results['records'] if r['fold'] == fold]
        zero = records[0]
        assert zero['k'] == 0
        # k = 0 is the fold's model, serving its new people as the fold-in starts them: the plain
        # encoder ('base_encoder'), or the prior's mean (with the head's wide rows, not the zero row)
        assert abs(zero['retrained']['mse'] - zero['fold-in (random)']['mse']) < 1e-6
        assert zero['fold-in (random)'] == zero['fold-in (active)']  # no question asked yet
        if strangers == 'base_encoder':
            assert abs(zero['fold-in (random)']['mse'] - zero['base encoder']['mse']) < 1e-6
        for record in records:  # the same test rows for every k the same people cover
            if record['covered'] == zero['covered']:
                assert record['n_test'] == zero['n_test'] and record['unpersonalised'] == zero['unpersonalised']
    calibration = results['calibration']
    assert set(calibration['new']) == {'0', '1', '2', '5'} and calibration['known']['n'] > 0
    for k, pooled in calibration['new'].items():  # each fold's own, pooled again, is the table's
        folds = [r['calibration'] for r in results['records'] if r['k'] == int(k)]
        weights = [f['n'] * f['draws'] for f in folds]
        assert len(folds) == 2 and sum(f['n'] for f in folds) == pooled['n']
        for level in ('0.5', '0.95'):
            assert np.average([f[level] for f in folds], weights=weights) == pytest.approx(pooled[level], abs=1e-12)
    assert set(results['goals']['never_worse']) == {'fold-in (random)', 'fold-in (active)'}
    assert all(record['base encoder']['n'] == record['n_test'] for record in records)  # the plain encoder beside
    assert set(results['goals']['hand_over']) == {'fold-in (random)', 'fold-in (active)'}
    text = (out / 'results.md').read_text()
    assert '| 5 |' in text and 'retrained' in text and '| known |' in text
    assert '| k | seed 0 fold 0 | seed 0 fold 1 |' in text  # the calibration per fold
    gaps = {fold: max(abs(100 * r['calibration'][level] - 100 * float(level)) for r in results['records']
                      if r['fold'] == fold for level in ('0.5', '0.8', '0.9', '0.95')) for fold in (0, 1)}
    per_fold = next(line for line in text.splitlines() if line.startswith('- the same in every fold'))
    assert per_fold.endswith(': met') == all(gap <= 3 for gap in gaps.values())
    assert all((f'0/{fold} ({gap:.1f})' in per_fold) == (gap > 3) for fold, gap in gaps.items())
    assert 'at or below unpersonalised MSE in every fold at every k ≥ 1' in capsys.readouterr().out


def test_the_hand_over_k_is_where_the_fold_in_stays_at_or_below_the_base_encoder_in_every_fold():
    def record(fold, k, fold_in, base):
        return {'fold': fold, 'k': k, 'fold-in (x)': {'mse': fold_in}, 'base encoder': {'mse': base}}
    records = [record(0, 0, 3.0, 2.0), record(1, 0, 3.0, 2.0), record(0, 1, 1.0, 2.0), record(1, 1, 2.5, 2.0),
               record(0, 2, 1.0, 2.0), record(1, 2, 2.0, 2.0), record(0, 5, 2.1, 2.0), record(1, 5, 1.0, 2.0),
               record(0, 10, 1.0, 2.0), record(1, 10, 1.0, 2.0)]
    assert kshot_report.hand_over_k(records, 'fold-in (x)') == 10  # k = 2 holds in both folds, k = 5 not in fold 0
    assert kshot_report.hand_over_k(records[:6], 'fold-in (x)') == 2
    assert kshot_report.hand_over_k([record(0, 0, 3.0, 2.0)], 'fold-in (x)') is None


def test_settings_are_chosen_per_fold_on_its_training_people_only(synthetic_root, synthetic, tmp_path, monkeypatch):
    """On the packaged config: a selection fit serves no stranger, so it fits no plain encoder;
    the kept fits do."""
    seen = []
    original = kshot_run.fit_rows

    def fit_rows(experiment, train, test, keep, data=None):
        if experiment['model'].get('variant') != 'base':  # the plain encoder beside each fold is not selection
            seen.append((experiment['training']['joint_epochs'], np.asarray(train), np.asarray(test), keep))
            assert experiment['model']['strangers'] == ('base_encoder' if keep else 'prior_mean')
        return original(experiment, train, test, keep, data)
    monkeypatch.setattr(kshot_run, 'fit_rows', fit_rows)
    out = tmp_path / 'kshot'
    assert kshot.main(['--config', 'config/socnav1_gat.yaml', '--data-root', str(synthetic_root), '--out',
                       str(out), '--quick', '--retrain-ks', '0', '--select', 'joint_epochs=1,3']) == 0
    results = json.loads((out / 'results.json').read_text())
    held_out = [set(people) for people in results['folds']['0']]
    assert len(results['selection']) == 2
    for entry, _ in zip(results['selection'], held_out):
        errors = entry['validation_mse']
        assert set(errors) == {'{"joint_epochs": 1}', '{"joint_epochs": 3}'}
        assert np.isfinite(list(errors.values())).all()  # no selection fit failed
        assert entry['chosen'] == json.loads(min(errors, key=errors.get))
    selection_fits = [fit for fit in seen if not fit[3]]  # with --retrain-ks 0 the only fits not kept
    assert len(selection_fits) == 4  # two candidates, two folds
    for people in held_out:  # each fold's two candidates saw none of its held-out people, in either part
        assert sum(set(synthetic.users[np.concatenate([train, validation])].tolist()).isdisjoint(people)
                   for _, train, validation, _ in selection_fits) == 2
    finals = [fit for fit in seen if fit[3]]
    assert sorted(fit[0] for fit in finals) == sorted(e['chosen']['joint_epochs'] for e in results['selection'])
    assert 'chosen per fold inside its training people' in (out / 'results.md').read_text()


@pytest.mark.slow
def test_fits_in_worker_processes_give_what_inline_fits_give(synthetic_root, tmp_path):
    """One seed's two folds with their fits (the folds' models and their retraining at k = 2)
    in 2 worker processes, then all inline: same records, in the same order (the folds' fits
    finish in either order in the pool)."""
    runs = {}
    for jobs in (2, 1):
        out = tmp_path / f'jobs{jobs}'
        assert kshot.main(['--config', 'config/socnav1_gat.yaml', '--data-root', str(synthetic_root), '--out', str(out),
                           '--quick', '--seeds', '3', '--retrain-ks', '0', '2', '--jobs', str(jobs)]) == 0
        runs[jobs] = json.loads((out / 'results.json').read_text())
    assert set(runs[2]['folds']) == {'3'}
    assert [(r['seed'], r['fold'], r['k']) for r in runs[2]['records']] == \
        [(3, fold, k) for fold in (0, 1) for k in (0, 1, 2, 5)]  # --quick's folds and ks
    assert len(runs[2]['records']) == len(runs[1]['records'])
    assert [r['k'] for r in runs[2]['records'] if 'retrained' in r] == [0, 2, 0, 2]
    for parallel, inline in zip(runs[2]['records'], runs[1]['records']):
        assert parallel.get('retrained') == inline.get('retrained')
        assert parallel['fold-in (random)'] == inline['fold-in (random)']
    assert runs[2]['jobs'] == 2 and runs[2]['seeds'] == [3]


def test_a_fold_whose_fit_fails_is_left_out_and_named(synthetic_root, tmp_path, monkeypatch, capsys):
    """The fifth fit (fold 1's retraining at k = 5: fold 0's four come first, each fold's
    largest first; the packaged config's fold model is its own base encoder) raises: fold 0
    is reported, fold 1 is named and left out, status 1."""
    calls, fit_rows = [], kshot_run.fit_rows

    def failing_fifth(*args, **kwargs):
        calls.append(args)
        if len(calls) == 5:
            raise RuntimeError('injected')
        return fit_rows(*args, **kwargs)

    monkeypatch.setattr(kshot_run, 'fit_rows', failing_fifth)
    out = tmp_path / 'kshot'
    assert kshot.main(['--config', 'config/socnav1_gat.yaml', '--data-root', str(synthetic_root), '--out', str(out),
                       '--quick']) == 1
    results = json.loads((out / 'results.json').read_text())
    assert not results['complete'] and {r['fold'] for r in results['records']} == {0}
    assert results['failed'] == [{'seed': 0, 'fold': 1, 'k': 5, 'error': 'RuntimeError: injected'}]
    assert 'seed 0 fold 1 k=5: RuntimeError: injected' in capsys.readouterr().err
