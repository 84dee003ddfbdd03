"""bench/insilico_study.py without training: budgets, run state, snapshots, results, tables,
ordering, the report and the task scheduler, on fake run folders."""

from __future__ import annotations

from fractions import Fraction
import json
from pathlib import Path
import re
import sys

from bench_modules import bench_module
import pytest

WS = Path(__file__).resolve().parent.parent
study = bench_module('insilico_study')
sweep = bench_module('sweep')


def write_scalars(run: Path, rows: list[tuple[int, str, float]], tail: str = '') -> None:
    run.mkdir(parents=True, exist_ok=True)
    lines = ['step,tag,value'] + [f'{s},{t},{v}' for s, t, v in rows]
    (run / 'scalars.csv').write_text('\n'.join(lines) + '\n' + tail)


def fake_run(run: Path, max_steps: int, reached: int, final: bool = True,
             checkpoints: tuple[int, ...] = (), state: int | None = None) -> Path:
    """A train run folder: config.yaml, scalars.csv up to ``reached``, final.pt, checkpoints."""
    write_scalars(run, [(1024 * i, 'time/steps_per_s', 500.0) for i in range(1, reached // 1024
                                                                              + 1)]
                  + [(reached, 'eval/success_rate', 0.5)])
    (run / 'config.yaml').write_text(f'name: smoke\nmax_steps: {max_steps}\n'
                                     'ppo: {buffer_size: 1024}\n')
    if final:
        (run / 'final.pt').write_bytes(b'final')
    for c in checkpoints:
        (run / 'checkpoints').mkdir(exist_ok=True)
        (run / 'checkpoints' / f'step_{c}.pt').write_bytes(b'ck')
    if state is not None:
        (run / 'study_state.json').write_text(json.dumps({'step': state}))
    return run


def write_results(folder: Path, name: str, mode: str, successes: list[bool]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    trials = [{'success': s, 'collision': not s, 'timesteps': 400, 'targeting_error_mm': 9.0}
              for s in successes]
    (folder / 'results.json').write_text(json.dumps(
        {'trials': len(trials), 'modes': {mode: {name: {'summary': {}, 'trials': trials}}}}))


# ---------------------------------------------------------------------------- inputs


def test_budgets_must_increase():
    assert study.check_budgets([4096, 8192]) == (4096, 8192)
    for bad, match in (([], 'one or more'), ([0, 10], '>= 1'),
                       ([8192, 4096], 'strictly increasing'), ([4096, 4096], 'increasing')):
        with pytest.raises(study.StudyError, match=match):
            study.check_budgets(bad)


@pytest.mark.parametrize('argv, message', [
    (['--methods', 'nope'], "--methods: expected a preset name in ["),
    (['--methods', 'smoke', '--steps', '8192', '4096'], '--steps: expected strictly increasing'),
    (['--methods', 'smoke', '--unseen-scenario-seed', '0'], '--unseen-scenario-seed: expected'),
    (['--methods', 'smoke', 'smoke'], '--methods: expected distinct values'),
    (['--methods', 'smoke', '--jobs', '0'], '--jobs: expected >= 1, found 0'),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, tmp_path, capsys):
    assert study.main([*argv, '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'insilico_study: error: {message}') and err.count('\n') == 1
    assert not (tmp_path / 'out').exists()


def test_method_names():
    assert study.method_kind('paper_code_gail') == 'gail'
    assert study.method_label('paper_code_mu0') == 'mu = 0 (no BC)'
    assert study.method_label('smoke') == 'smoke'


# ---------------------------------------------------------------------------- run state


def test_scalars_skip_a_half_written_row_and_give_progress(tmp_path):
    write_scalars(tmp_path, [(1024, 'time/steps_per_s', 512.0),
                             (2048, 'eval/success_rate', 0.25),
                             (2048, 'time/steps_per_s', 1024.0)], tail='3072,time/st')
    sc = study.read_scalars(tmp_path / 'scalars.csv')
    assert sc['eval/success_rate'] == [(2048, 0.25)] and study.last_step(sc) == 2048
    p = study.run_progress(tmp_path)
    assert p == study.Progress(2048, 1024.0, 2048, 0.25)
    assert p.line(4096) == ('2,048/4,096 steps (50%), 1,024 steps/s, ETA 2 s, '
                            'last eval success 0.25 at 2,048')
    assert study.run_progress(tmp_path / 'none').line(10) == '0/10 steps (0%)'
    # steps/s only from the rows of the running process (past the step it resumed from)
    assert study.run_progress(tmp_path, since=2048).steps_per_s is None


def test_a_finished_run_needs_no_training(tmp_path):
    run = fake_run(tmp_path / 'run', 4096, 4096)
    assert study.trained_to(run, 4096) and not study.trained_to(run, 8192)
    assert study.train_command(run, 4096, ['--preset', 'smoke'], ['--mode', 'static']) is None


def test_a_larger_budget_resumes_the_run(tmp_path):
    # the 4096 invocation ended (study_state), then a resume to 8192 was stopped at 6144
    run = fake_run(tmp_path / 'run', 8192, 6144, state=4096)
    assert study.resumable_step(run) == 4096
    cmd = study.train_command(run, 8192, ['--preset', 'smoke'], ['--mode', 'static'])
    assert cmd[1:] == ['-m', 'cgail_learning.train', '--resume', str(run),
                       '--max-steps', '8192', '--mode', 'static']


def test_a_resume_deletes_the_superseded_checkpoints(tmp_path):
    run = fake_run(tmp_path / 'run', 8192, 6144, checkpoints=(2048, 4096, 6144), final=False)
    cmd = study.train_command(run, 8192, ['--preset', 'smoke'], [])
    assert cmd[cmd.index('--resume') + 1] == str(run)
    assert sorted(p.name for p in (run / 'checkpoints').iterdir()) == ['step_6144.pt']


def test_a_run_past_the_budget_cannot_give_it(tmp_path):
    run = fake_run(tmp_path / 'run', 16384, 12288, checkpoints=(5120, 10240))
    assert study.resumable_step(run) == 10240
    with pytest.raises(study.StudyError, match='at 10,240: that budget was not snapshotted'):
        study.train_command(run, 8192, ['--preset', 'smoke'], [])


def test_a_run_without_checkpoint_starts_again(tmp_path):
    run = fake_run(tmp_path / 'run', 4096, 2048, final=False)
    cmd = study.train_command(run, 4096, ['--preset', 'smoke', '--seed', '1'], ['--mode', 'x'])
    assert cmd[1:] == ['-m', 'cgail_learning.train', '--preset', 'smoke', '--seed', '1',
                       '--max-steps', '4096', '--out', str(run), '--mode', 'x']
    assert not run.exists()


def test_snapshot_keeps_the_budget_and_refuses_another(tmp_path):
    run = fake_run(tmp_path / 'run', 4096, 4096)
    (run / 'best.pt').write_bytes(b'best')
    log = tmp_path / 'train.log'
    log.write_text('=== start\ntime/steps_per_s: 900.0\ntime/wall_s: 12.5\n')
    study.snapshot(run, tmp_path / 'steps_4096', 4096, log)
    info = json.loads((tmp_path / 'steps_4096' / 'snapshot.json').read_text())
    assert {k: info[k] for k in ('budget', 'step', 'policy', 'best_eval_success', 'wall_s')} == {
        'budget': 4096, 'step': 4096, 'policy': 'best.pt', 'best_eval_success': 0.5,
        'wall_s': 12.5}
    assert (tmp_path / 'steps_4096' / 'best.pt').read_bytes() == b'best'
    with pytest.raises(study.StudyError, match='expected the run at 2,048 steps'):
        study.snapshot(run, tmp_path / 'steps_2048', 2048, log)


# ---------------------------------------------------------------------------- results


def test_outcomes_pool_over_seeds_and_round_half_up():
    a, b = study.Outcome(3, 4), study.Outcome(1, 4)
    assert study.mean_outcome([a, b]) == study.Outcome(4, 8)
    assert study.mean_outcome([a, None]) is None
    assert [study.percent(Fraction(n, d)) for n, d in ((1, 2), (2, 3), (1, 200), (0, 1))] == [
        '50%', '67%', '1%', '0%']


def test_load_outcome_counts_successes(tmp_path):
    write_results(tmp_path, 'cgail', 'static', [True, False, True])
    assert study.load_outcome(tmp_path) == study.Outcome(2, 3)
    assert study.load_outcome(tmp_path, 'other') is None
    assert study.load_outcome(tmp_path / 'none') is None


PAPER_STATIC = {m: Fraction(v, 100) for m, v in (('cgail', 80), ('gail', 42), ('mu0', 11),
                                                 ('lambda0', 58), ('nu0', 48))}


def test_ordering_groups_ties():
    assert study.ordering(PAPER_STATIC) == [['cgail'], ['lambda0'], ['nu0'], ['gail'], ['mu0']]
    ours = {'cgail': Fraction(1), 'gail': Fraction(0), 'mu0': Fraction(0),
            'lambda0': Fraction(1), 'nu0': Fraction(97, 100)}
    assert study.ordering(ours, study.TIE) == [['cgail', 'lambda0', 'nu0'], ['gail', 'mu0']]
    assert study.format_ordering(ours, study.TIE, study.method_label) == (
        'C-GAIL 100% ≈ lambda = 0 (no GAIL) 100% ≈ nu = 0 (no curiosity) 97% > GAIL 0% '
        '≈ mu = 0 (no BC) 0%')


def test_pair_agreement_counts_the_paper_order():
    ours = {'cgail': Fraction(1), 'gail': Fraction(0), 'mu0': Fraction(0),
            'lambda0': Fraction(1), 'nu0': Fraction(97, 100)}
    agree, total, differ = study.pair_agreement(ours, PAPER_STATIC)
    assert (agree, total) == (6, 10)
    assert sorted(differ) == sorted([('cgail', 'lambda0'), ('cgail', 'nu0'),
                                     ('lambda0', 'nu0'), ('gail', 'mu0')])
    assert study.pair_agreement(PAPER_STATIC, PAPER_STATIC) == (10, 10, [])


def test_paper_figures():
    assert study.PAPER_SUCCESS == {
        ('cgail', 'static'): 80, ('gail', 'static'): 42, ('mu0', 'static'): 11,
        ('lambda0', 'static'): 58, ('nu0', 'static'): 48, ('cgail', 'dynamic'): 17,
        ('gail', 'dynamic'): 0}
    assert study.PAPER_SECOND_ANATOMY == 79
    assert (study.AUTHORS_STEPS['gail'], study.AUTHORS_STEPS['cgail']) == (5_000_000, 8_000_000)


@pytest.fixture
def fake_study(tmp_path):
    """Two methods x two seeds x two budgets, static and dynamic; GAIL seed 1 stopped at
    6,144 of 8,192 steps."""
    layout = study.Layout(tmp_path / 'out')
    plan = study.StudyPlan(('cgail', 'gail'), (0, 1), (4096, 8192), ('static', 'dynamic'),
                           {'cgail': 'ours', 'gail': 'ours'}, trials=4)
    wins = {'cgail': [4, 3], 'gail': [1, 0]}
    for m in plan.methods:
        for s in plan.seeds:
            run = layout.static_run(m, s)
            reached = 6144 if (m, s) == ('gail', 1) else 8192
            write_scalars(run, [(4096, 'eval/success_rate', 0.25 * (s + 1)),
                                (reached, 'eval/success_rate', 0.5)])
            for n in plan.budgets:
                if n > reached:
                    continue
                layout.budget(m, s, n).mkdir(parents=True)
                layout.snapshot(m, s, n).write_text(json.dumps({'step': n + 1024,
                                                                'wall_s': 60.0}))
                write_scalars(layout.dynamic_run(m, s, n), [(2048, 'eval/success_rate', 0.75)])
                for mode in plan.modes:
                    for k in plan.target_sets:
                        won = wins[m][s] - (k == 1)
                        write_results(layout.evaluation(m, s, n, mode, k), m, mode,
                                      [i < won for i in range(4)])
    write_results(layout.baselines('ours', 'static', 0), 'centerline', 'static', [True] * 4)
    return layout, plan


def test_collect_and_the_report(fake_study):
    layout, plan = fake_study
    res = study.collect(layout, plan)
    assert res.outcomes[('cgail', 1, 8192, 'static', 1)] == study.Outcome(2, 4)
    assert ('gail', 1, 8192, 'static', 0) not in res.outcomes
    assert res.reached[('gail', 1, 8192)] == 6144
    path = study.write_report(layout, plan, 'scripts/ws python bench/insilico_study.py')
    report = path.read_text()
    ci = '95% CI 0-100%'  # two seeds: t(0.975, 1) = 12.7
    assert (f'| C-GAIL (`cgail`) | 5,120 (authors: 8,000,000) | 80% | 100%, 75% (mean **88%**, '
            f'{ci}) | 75%, 50% (mean **63%**, {ci}) | 17% | 100%, 75% (mean **88%**, {ci}) | '
            f'75%, 50% (mean **63%**, {ci}) |') in report
    assert ('| GAIL (`gail`) | seed 0: 9,216, seed 1: 6,144 of 8,192 † (authors: 5,000,000; '
            'stopped at 1,275,443) | 42% | 25%, - (mean -) |') in report
    # the summary: every method and budget with all seeds evaluated, range and both intervals
    assert ('| GAIL (`gail`) | 4,096 (5,000,000; stopped at 1,275,443) | static | unseen | '
            '0%, 0% | **0%** | 0-0% | 0-0% | 0-32% | - |') in report
    summary = (layout.root / 'summary.csv').read_text().splitlines()
    assert summary[0] == ','.join(study.SUMMARY_HEAD) and len(summary) == 1 + 12
    assert ('default,ours,cgail,8192,static,training,0 1,"100%, 75%",88%,75-100%,0-100%,53-98%,'
            '80%') in summary
    assert '- static, paper: C-GAIL 80% > GAIL 42%' in report
    assert ('- static, training targets: C-GAIL 88% > GAIL 13%; 1 of 1 pairs ordered as in the '
            'paper') in report
    assert '`centerline` static 100% / -' in report
    assert (layout.root / 'curves_ours_static.png').stat().st_size > 0
    assert (layout.root / 'curves_ours_dynamic.png').stat().st_size > 0
    rows = (layout.root / 'results.csv').read_text().splitlines()
    assert rows[0] == 'anatomy,options,preset,seed,budget,steps,mode,targets,successes,trials'
    # per seed and budget 2 modes x 2 target sets; GAIL seed 1 has only its first budget
    assert len(rows) == 1 + 4 * (2 * 2 + 2 + 1)
    assert 'default,ours,cgail,1,8192,9216,static,unseen (scenario seed 1),2,4' in rows


def test_the_report_places_the_hand_written_reasons_after_its_tables(fake_study):
    layout, plan = fake_study
    report = study.write_report(layout, plan, 'cmd').read_text()
    assert study.REASONS_HEADING not in report  # no reasons.md: no section
    (layout.root / study.REASONS).write_text('GAIL never reached a target in training.\n')
    report = study.write_report(layout, plan, 'cmd').read_text()
    head = report.index(study.REASONS_HEADING)
    assert report.index('GAIL never reached a target in training.') > head
    assert report.rindex('### ') < head  # after the last budget's table
    (layout.root / study.REASONS).write_text('## Reasons\n\nBC finds the path.\n')
    report = study.write_report(layout, plan, 'cmd').read_text()
    assert '## Reasons\n\nBC finds the path.' in report
    assert study.REASONS_HEADING not in report  # its own heading is kept


def test_a_command_without_some_of_the_folders_presets_says_it_leaves_them_out(fake_study,
                                                                                 capsys):
    layout, plan = fake_study
    (layout.root / 'logs').mkdir()  # the study's own folders are not presets
    (layout.root / 'gail' / 'notes').mkdir()
    assert study.left_out(layout, plan) == []
    only = study.StudyPlan(('cgail',), plan.seeds, plan.budgets, plan.modes,
                           {'cgail': 'ours'}, trials=4)
    assert study.left_out(layout, only) == ['gail']
    argv = ['--methods', 'cgail', '--seeds', '0', '1', '--steps', '4096', '8192', '--trials',
            '4', '--out', str(layout.root), '--report-only']
    assert study.main(argv) == 0
    out = capsys.readouterr().out
    assert f'note: {layout.root} also holds runs of gail, which this command leaves out' in out
    report = (layout.root / 'report.md').read_text()
    assert '(`cgail`)' in report and '(`gail`)' not in report  # what the note warns of
    assert study.main([*argv[:1], 'cgail', 'gail', *argv[2:]]) == 0
    assert 'also holds' not in capsys.readouterr().out
    # the sweep says the same of its configuration's presets
    cfg = layout.root.parent / 'only_cgail.yaml'
    cfg.write_text('presets: [cgail]\nseeds: [0, 1]\nbudgets: [4096, 8192]\ntrials: 4\n'
                   'anatomies: [default]\n')
    assert sweep.main([str(cfg), '--out', str(layout.root), '--report-only']) == 0
    assert 'also holds runs of gail' in capsys.readouterr().out


#: The README's reproduction table: its row labels and the presets behind its columns.
README_ROWS = {'C-GAIL': ('paper_code_cgail', 'cgail'), 'GAIL': ('paper_code_gail', 'gail'),
               'mu = 0 (no BC)': (None, 'mu0'), 'lambda = 0 (no GAIL)': (None, 'lambda0'),
               'nu = 0 (no curiosity)': (None, 'nu0')}


def test_the_readme_reproduction_table_is_the_committed_study():
    """Every figure of the README's "The paper's figures, reproduced" table is the committed
    study's (``studies/insilico_authors/summary.csv``, training targets), every budget of a
    preset when the cell says "at both"."""
    import csv
    with (WS / 'studies' / 'insilico_authors' / 'summary.csv').open() as f:
        rows = [r for r in csv.DictReader(f) if r['targets'] == 'training']
    lines = (WS / 'README.md').read_text().splitlines()
    head = lines.index('| method | budget | static: paper | static: `paper_code` | static: '
                       '`ours` | beating: paper | beating: `paper_code` | beating: `ours` |')
    checked = 0
    for line in lines[head + 2:]:
        if not line.startswith('|'):
            break
        cells = [c.strip() for c in line.strip('|').split('|')]
        presets = README_ROWS[cells[0]]
        for mode, (theirs, ours) in (('static', cells[3:5]), ('dynamic', cells[6:8])):
            for preset, cell in zip(presets, (theirs, ours), strict=True):
                got = re.fullmatch(r'(\d+)% \(([\d, ]+)\)( at both)?', cell)
                if preset is None or got is None:
                    assert preset is None or cell in ('not run', 'C-GAIL itself', '-'), cell
                    continue
                study_rows = [r for r in rows if (r['preset'], r['mode']) == (preset, mode)]
                assert len(study_rows) == (2 if got[3] else 1), (preset, mode)
                for r in study_rows:
                    assert (r['mean'], r['per seed']) == (
                        f'{got[1]}%', ', '.join(f'{v}%' for v in got[2].split(', ')))
                    checked += 1
    assert checked >= 8


# ---------------------------------------------------------------------------- tasks


def test_plan_tasks_chain_budgets_and_modes(tmp_path):
    layout = study.Layout(tmp_path)
    plan = study.StudyPlan(('smoke',), (0,), (4096, 8192), ('static', 'dynamic'),
                           {'smoke': 'ours'})
    tasks = {t.key: t for t in study.plan_tasks(layout, plan)}
    assert len(tasks) == 2 * (1 + 1 + 2 + 4) + 4
    assert tasks['smoke/seed0/8192/train-static'].deps == ['smoke/seed0/4096/train-static']
    assert tasks['smoke/seed0/4096/train-dynamic'].deps == ['smoke/seed0/4096/train-static']
    assert tasks['smoke/seed0/8192/eval-dynamic-targets1'].deps == [
        'smoke/seed0/8192/export-dynamic']
    cmd = tasks['smoke/seed0/4096/train-dynamic'].command()
    assert cmd[cmd.index('--init-from') + 1] == str(layout.budget('smoke', 0, 4096) / 'best.pt')
    for task in tasks.values():  # (a stopped session loses at most the study's interval)
        if task.kind == 'train':
            cmd = task.command()
            assert cmd[cmd.index('--checkpoint-every') + 1] == str(study.CHECKPOINT_EVERY)
    cmd = tasks['smoke/seed0/4096/eval-static-targets1'].command()
    assert cmd[cmd.index('--scenario-seed') + 1] == '1' and '--baselines' in cmd


def _touch_task(key: str, out: Path, deps: list[str], code: str = '') -> object:
    marker = out / f'{key}.done'
    script = code or f'open({str(marker)!r}, "w").write("x")'
    return study.Task(key, 'eval', deps, done=marker.is_file,
                      command=lambda: [sys.executable, '-c', script])


def test_run_tasks_runs_what_a_task_without_a_process_made_ready(tmp_path):
    """A task with nothing to run (a budget's snapshot) finishes at once; what depends on it
    runs in the same invocation rather than being left for the next one."""
    layout = study.Layout(tmp_path)
    marker = tmp_path / 'snap.done'

    def snap() -> None:
        marker.write_text('x')

    tasks = [study.Task('snap', 'export', [], done=marker.is_file, command=lambda: None,
                        post=snap),
             _touch_task('export', tmp_path, ['snap']), _touch_task('eval', tmp_path, ['export'])]
    assert study.run_tasks(tasks, layout, 2, 3600.0) == (3, 0)
    assert (tmp_path / 'eval.done').is_file()


def test_run_tasks_follows_dependencies_and_blocks_after_a_failure(tmp_path, capsys):
    layout = study.Layout(tmp_path)
    tasks = [_touch_task('b', tmp_path, ['a']), _touch_task('a', tmp_path, []),
             _touch_task('bad', tmp_path, [], code='import sys; print("boom"); sys.exit(3)'),
             _touch_task('after-bad', tmp_path, ['bad'])]
    finished: list[str] = []
    assert study.run_tasks(tasks, layout, 2, 3600.0,
                           lambda t: finished.append(t.key)) == (2, 2)
    assert finished == ['a', 'b']
    failed = [ln for ln in capsys.readouterr().out.splitlines() if 'FAILED' in ln]
    assert len(failed) == 1 and ' FAILED bad: exit 3 after ' in failed[0]
    assert failed[0].endswith(': boom')
    assert not (tmp_path / 'after-bad.done').exists()
    assert 'boom' in (tmp_path / 'logs' / 'bad.log').read_text()
    # a second run skips what is done
    assert study.run_tasks(tasks[:2], layout, 1, 3600.0) == (2, 0)
    assert '2 tasks: 2 already done, 0 to run' in capsys.readouterr().out


def test_an_evaluation_is_redone_for_a_new_policy_or_another_trial_count(tmp_path):
    import os

    policy = tmp_path / 'static.onnx'
    policy.write_bytes(b'onnx')
    folder = tmp_path / 'eval'
    write_results(folder, 'cgail', 'static', [True, False])
    data = json.loads((folder / 'results.json').read_text())
    data['trials'] = 2
    (folder / 'results.json').write_text(json.dumps(data))
    os.utime(policy, (1_000, 1_000))
    assert study.evaluated(folder, policy, 2) and study.evaluated(folder, None, 2)
    assert not study.evaluated(folder, policy, 100)
    os.utime(policy, (4e9, 4e9))  # re-exported after the evaluation
    assert not study.evaluated(folder, policy, 2)
    assert not study.up_to_date(tmp_path / 'none.onnx', policy)


@pytest.mark.parametrize('name', ['pure_gail_ours_ppo', 'pure_gail_ours_ppo_normalised',
                                  'pure_gail_sb3_defaults', 'gail'])
def test_the_gail_variants_of_the_readme_load_as_described(name):
    """bench/gail_variants/*.yaml (docs/reports/gail_baseline.md) stay valid presets and pure
    GAIL at imitation's discriminator pace, as that report's table says."""
    from cgail_learning.config import load_config

    cfg = load_config(name if name == 'gail' else WS / 'bench' / 'gail_variants' / f'{name}.yaml')
    assert cfg.extrinsic.strength == 0.0 and cfg.gail.strength == 1.0
    assert cfg.bc.strength == 0.0 and cfg.curiosity.strength == 0.0
    assert (cfg.gail.reward_form, cfg.gail.gradient_penalty) == ('standard', 0.0)
    assert (cfg.gail.updates_per_buffer, cfg.gail.batch_size) == (4, 1024)
    assert cfg.max_steps == 2_000_000 and cfg.ppo.schedule == 'constant'
    matched = name == 'gail'  # the preset: imitation's GAIL on SB3's PPO defaults
    assert cfg.normalize == (name not in ('pure_gail_ours_ppo', 'gail'))
    assert cfg.gail.use_actions == (name in ('pure_gail_sb3_defaults', 'gail'))
    assert cfg.gail.own_normalizer == matched and cfg.network.orthogonal_init == matched
    assert (cfg.ppo.advantage_normalization, cfg.ppo.clip_value_loss) == (
        ('minibatch', False) if matched else ('buffer', True))


def test_the_bc_initialised_gail_variant_is_the_ml_agents_gail_plus_a_warm_start():
    from cgail_learning.config import config_to_dict, load_config

    variant = config_to_dict(load_config(WS / 'bench' / 'gail_variants' / 'gail_bc_init.yaml'))
    preset = config_to_dict(load_config(WS / 'bench' / 'gail_variants' / 'gail_ml_agents.yaml'))
    assert variant['bc'] == {**preset['bc'], 'pretrain_epochs': 30}
    assert variant['max_steps'] == 2_000_000
    for key in ('bc', 'max_steps', 'name'):
        variant.pop(key), preset.pop(key)
    assert variant == preset


# ---------------------------------------------------------------------------- anatomies


def test_an_anatomy_axis_keeps_the_default_anatomy_where_it_was(tmp_path):
    """The default anatomy's runs, keys and logs stay where a study without the axis had them
    (so such a study resumes); another anatomy's lie under anatomies/<name>/, its keys carry
    its name, and every train and evaluate invocation in it is told so."""
    layout = study.Layout(tmp_path)
    elongated = study.Anatomy.named('elongated')
    assert elongated == study.Anatomy('elongated', ('--anatomy', 'elongated'),
                                      ('--anatomy', 'elongated'),
                                      (WS / 'bags' / 'demos' / 'elongated',))
    plan = study.StudyPlan(('smoke',), (0,), (4096,), ('static',), {'smoke': 'ours'},
                           anatomies=(study.Anatomy.named('default'), elongated))
    tasks = {t.key: t for t in study.plan_tasks(layout, plan)}
    assert len(tasks) == 2 * (1 + 1 + 2 + 2)
    assert tasks['smoke/seed0/4096/train-static'].run == tmp_path / 'smoke' / 'seed0' / 'static'
    assert tasks['elongated/smoke/seed0/4096/train-static'].run == (
        tmp_path / 'anatomies' / 'elongated' / 'smoke' / 'seed0' / 'static')
    cmd = tasks['elongated/smoke/seed0/4096/train-static'].command()
    assert cmd[cmd.index('--anatomy') + 1] == 'elongated'
    assert cmd[cmd.index('--demos') + 1] == str(WS / 'bags' / 'demos' / 'elongated')
    cmd = tasks['elongated/smoke/seed0/4096/eval-static-targets1'].command()
    assert cmd[cmd.index('--anatomy') + 1] == 'elongated'
    assert cmd[cmd.index('--out') + 1] == str(layout.of_anatomy('elongated').evaluation(
        'smoke', 0, 4096, 'static', 1))
    assert 'elongated/baselines/ours/static-targets0' in tasks
    assert layout.log('elongated/smoke/seed0/4096/train-static') == (
        tmp_path / 'logs' / 'elongated_smoke_seed0_4096_train-static.log')


def test_an_anatomy_that_does_not_exist_is_one_line():
    with pytest.raises(study.StudyError, match=r"^anatomy: expected a built-in anatomy name "
                                               r"\['default', 'elongated'\]"):
        study.Anatomy.named('no/such/aorta')


def test_the_report_of_two_anatomies_is_one_table(tmp_path):
    layout = study.Layout(tmp_path / 'out')
    anatomies = (study.Anatomy.named('default'), study.Anatomy.named('elongated'))
    plan = study.StudyPlan(('cgail',), (0,), (4096,), ('static',), {'cgail': 'ours'}, trials=4,
                           anatomies=anatomies)
    for a, won in (('default', 3), ('elongated', 1)):
        at = layout.of_anatomy(a)
        at.budget('cgail', 0, 4096).mkdir(parents=True)
        at.snapshot('cgail', 0, 4096).write_text(json.dumps({'step': 4096}))
        write_scalars(at.static_run('cgail', 0), [(4096, 'eval/success_rate', 0.5)])
        for k in plan.target_sets:
            write_results(at.evaluation('cgail', 0, 4096, 'static', k), 'cgail', 'static',
                          [i < won for i in range(4)])
    report = study.write_report(layout, plan, 'sweep').read_text()
    assert '| anatomy | method | steps used' in report
    row = '| `{}` | C-GAIL (`cgail`) | 4,096 (authors: 8,000,000) | {} | **{}** |'
    assert row.format('default', '80%', '75%') in report
    assert row.format('elongated', '-', '25%') in report
    assert (layout.root / 'curves_ours_static.png').is_file()
    assert (layout.root / 'curves_elongated_ours_static.png').is_file()
    rows = (layout.root / 'results.csv').read_text().splitlines()
    assert 'elongated,ours,cgail,0,4096,4096,static,training,1,4' in rows and len(rows) == 5


# ---------------------------------------------------------------------------- fresh budgets


def test_the_authors_budgets_per_method():
    """Their GAIL run was configured for 5M and stopped at 1,275,443 (training_status.json);
    their C-GAIL ran 8M; an ablation gets their C-GAIL's 8M; ours their preset's max_steps."""
    assert study.AUTHORS_STOPPED == {'gail': 1_275_443}
    assert study.authors_budgets('gail') == (1_275_443, 5_000_000)
    assert study.authors_budgets('cgail') == (8_000_000,)
    assert study.authors_budgets('smoke') == ()
    options = {'paper_code_cgail': 'paper_code', 'paper_code_gail': 'paper_code',
               'paper_code_mu0': 'paper_code', 'cgail': 'ours', 'gail': 'ours'}
    steps = {'paper_code_cgail': 1, 'paper_code_gail': 1, 'paper_code_mu0': 1,
             'cgail': 500_000, 'gail': 2_000_000}
    assert study.method_budgets(options, steps) == {
        'paper_code_cgail': (8_000_000,), 'paper_code_gail': (1_275_443, 5_000_000),
        'paper_code_mu0': (8_000_000,), 'cgail': (500_000,), 'gail': (2_000_000,)}
    small = study.method_budgets(options, steps, 0.001)
    assert small['paper_code_gail'] == (1_275, 5_000) and small['cgail'] == (500,)
    assert study.method_budgets({'x': 'ours'}, {'x': 10}, 1e-6) == {'x': (1,)}
    with pytest.raises(study.StudyError, match=r'--budget-scale: expected a factor in \(0, 1\]'):
        study.method_budgets(options, steps, 2.0)


def test_intervals_over_seeds_and_pooled_trials():
    lo, hi = study.t_interval([0.5, 0.6, 0.7])  # mean 0.6, s 0.1, t(0.975, 2) 4.303
    assert (lo, hi) == pytest.approx((0.6 - 0.248414, 0.6 + 0.248414), abs=1e-6)
    assert study.t_interval([1.0, 0.0, 1.0]) == (0.0, 1.0)  # clipped
    assert study.t_interval([1.0, 1.0, 1.0]) == (1.0, 1.0)  # the seeds agree: no width
    assert study.t_interval([0.5]) is None
    assert study.wilson_interval(study.Outcome(8, 10)) == pytest.approx((0.4902, 0.9433),
                                                                        abs=1e-4)
    assert study.wilson_interval(study.Outcome(0, 300))[1] == pytest.approx(0.01264, abs=1e-5)
    st = study.seed_stats([study.Outcome(100, 100), study.Outcome(90, 100),
                           study.Outcome(50, 100)])
    assert st.mean == Fraction(4, 5) and st.range == (0.5, 1.0)
    assert study.span(st.t95) == '14-100%' and study.span(st.wilson95) == '75-84%'
    assert study.span(None) == '-' and study.seed_stats([study.Outcome(1, 2), None]) is None


def test_fresh_budgets_are_runs_of_their_own(tmp_path):
    """With fresh budgets no budget waits for another: each trains from scratch to its own
    max_steps in budget_<N>/static/, per-method budgets, seed by seed."""
    layout = study.Layout(tmp_path)
    plan = study.StudyPlan(('paper_code_gail', 'smoke'), (0, 1), (2048, 4096, 8192),
                           ('static', 'dynamic'), {'paper_code_gail': 'paper_code',
                                                   'smoke': 'ours'}, fresh=True,
                           method_budgets={'paper_code_gail': (2048, 8192), 'smoke': (4096,)})
    tasks = {t.key: t for t in study.plan_tasks(layout, plan)}
    assert len(tasks) == 2 * 3 * (1 + 1 + 2 + 4) + 2 * 4
    assert 'smoke/seed0/8192/train-static' not in tasks
    big = tasks['paper_code_gail/seed1/8192/train-static']
    assert big.deps == [] and big.target == 8192
    fresh_layout = study.Layout(tmp_path, fresh=True)
    assert big.run == tmp_path / 'paper_code_gail' / 'seed1' / 'budget_8192' / 'static'
    assert big.run == fresh_layout.static_run('paper_code_gail', 1, 8192)
    assert big.command()[1:] == ['-m', 'cgail_learning.train', '--preset', 'paper_code_gail',
                                 '--seed', '1', '--max-steps', '8192', '--out', str(big.run),
                                 '--mode', 'static', *big.command()[-9:]]
    # seed 0 of every method and budget before seed 1
    assert [tasks[f'paper_code_gail/seed{s}/8192/train-{m}'].order
            for s in (0, 1) for m in ('dynamic', 'static')] == [1, 2, 11, 12]
    cmd = tasks['smoke/seed0/4096/train-dynamic'].command()
    assert cmd[cmd.index('--init-from') + 1] == str(
        tmp_path / 'smoke' / 'seed0' / 'budget_4096' / 'best.pt')
    # an unfinished budget resumes from its own latest checkpoint
    fake_run(big.run, 8192, 6144, final=False, checkpoints=(5120,))
    assert big.command()[1:5] == ['-m', 'cgail_learning.train', '--resume', str(big.run)]
    with pytest.raises(ValueError, match='one static run per budget'):
        fresh_layout.static_run('smoke', 0)


def test_the_report_of_fresh_per_method_budgets(tmp_path):
    """Per-method budgets: each budget's table holds the methods that train to it, and the
    orderings compare every method at its largest and at its smallest budget."""
    layout = study.Layout(tmp_path / 'out', fresh=True)
    plan = study.StudyPlan(('paper_code_cgail', 'paper_code_gail'), (0, 1, 2), (2048, 4096, 8192),
                           ('static',), {m: 'paper_code' for m in ('paper_code_cgail',
                                                                   'paper_code_gail')},
                           trials=4, fresh=True,
                           method_budgets={'paper_code_cgail': (8192,),
                                           'paper_code_gail': (2048, 4096)})
    wins = {('paper_code_cgail', 8192): 4, ('paper_code_gail', 2048): 0,
            ('paper_code_gail', 4096): 3}
    for (m, n), won in wins.items():
        for s in plan.seeds:
            write_scalars(layout.static_run(m, s, n), [(n // 2, 'eval/success_rate', 0.1 * s),
                                                       (n, 'eval/success_rate', 0.5)])
            layout.snapshot(m, s, n).write_text(json.dumps({'step': n, 'wall_s': 30.0}))
            for k in plan.target_sets:
                write_results(layout.evaluation(m, s, n, 'static', k), m, 'static',
                              [i < won - (s == 2) for i in range(4)])
    report = study.write_report(study.Layout(tmp_path / 'out'), plan, 'cmd').read_text()
    assert 'Static: `train --mode static --max-steps N` from scratch for every budget' in report
    assert '`paper_code_gail` 2,048, 4,096' in report
    assert '### 8,192 steps' in report and '### 2,048 steps' in report
    section = report.split('### 2,048 steps')[1].split('###')[0]
    assert 'C-GAIL' not in section.split('Ordering')[0]
    assert ('| C-GAIL (`paper_code_cgail`) | 8,192 (authors: 8,000,000) | 80% | 100%, 100%, 75% '
            '(mean **92%**, 95% CI 56-100%) |') in report
    assert 'fewer than two methods' not in report  # one method per budget: no ordering there
    assert ('Ordering, each method at its largest budget (C-GAIL 8,192, GAIL 4,096) (ties: '
            'within 5 points):\n\n- static, paper: C-GAIL 80% > GAIL 42%\n- static, training '
            'targets: C-GAIL 92% > GAIL 67%; 1 of 1 pairs ordered as in the paper') in report
    assert 'each method at its smallest budget (C-GAIL 8,192, GAIL 2,048)' in report
    assert 'Training wall time (each run, from `train`)' in report
    assert (tmp_path / 'out' / 'curves_paper_code_static.png').stat().st_size > 0
    curves = study.static_curves(study.collect(layout, plan), 'paper_code')
    assert list(curves)[:2] == ['paper_code_cgail 8,192 steps seed 0',
                                'paper_code_cgail 8,192 steps seed 1']
    assert curves['paper_code_gail 2,048 steps seed 2'] == [(1024, 0.2), (2048, 0.5)]


@pytest.mark.parametrize('argv, message', [
    (['--authors-budgets', '--steps', '4096'], '--steps: expected no budgets with'),
    (['--budget-scale', '0.5'], '--budget-scale: expected only with --authors-budgets'),
    (['--authors-budgets', '--budget-scale', '0'], '--budget-scale: expected a factor in'),
])
def test_bad_budget_options_are_one_line(argv, message, tmp_path, capsys):
    assert study.main(['--methods', 'smoke', *argv, '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'insilico_study: error: {message}') and err.count('\n') == 1


def test_authors_budgets_plan_and_command():
    args = study.build_parser().parse_args(
        ['--methods', 'paper_code_gail', 'gail', '--authors-budgets', '--fresh-budgets',
         '--budget-scale', '0.001', '--seeds', '0', '1', '2'])
    plan = study.check_args(args)
    assert plan.fresh and plan.method_budgets == {'paper_code_gail': (1_275, 5_000),
                                                  'gail': (2_000,)}
    assert plan.budgets == (1_275, 2_000, 5_000) and plan.budgets_of('gail') == (2_000,)
    cmd = study.command_line(args)
    assert '--authors-budgets --budget-scale 0.001 --fresh-budgets' in cmd
    assert '--steps' not in cmd
    default = study.check_args(study.build_parser().parse_args(['--methods', 'smoke']))
    assert default.budgets == study.DEFAULT_STEPS and not default.fresh
    assert '--steps 500000 2000000 --modes' in study.command_line(
        study.build_parser().parse_args(['--methods', 'smoke']))


# ---------------------------------------------------------------------------- resuming in a clone


def _budget_done(layout, plan, s: int = 0, n: int = 4096) -> None:
    """Every output of budget ``n`` as the study makes them, content records included; the
    static run (continued) then stopped at 6144 of 8192 with periodic checkpoints."""
    run = fake_run(layout.static_run('smoke', s, n), n, n, state=n)
    (run / 'best.pt').write_bytes(b'static best')
    log = layout.log('x')
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text('time/wall_s: 1.0\n')
    study.snapshot(run, layout.budget('smoke', s, n), n, log)
    dyn = fake_run(layout.dynamic_run('smoke', s, n), plan.dynamic_steps, plan.dynamic_steps,
                   checkpoints=(1024,))
    (dyn / 'best.pt').write_bytes(b'dynamic best')
    study.record_state(dyn)
    for mode, ckpt in (('static', layout.budget('smoke', s, n) / 'best.pt'),
                       ('dynamic', dyn / 'best.pt')):
        policy = layout.policy('smoke', s, n, mode)
        policy.write_bytes(f'onnx of {ckpt.read_bytes()!r}'.encode())
        study.record_export(ckpt, policy)
        for k in plan.target_sets:
            folder = layout.evaluation('smoke', s, n, mode, k)
            write_results(folder, 'smoke', mode, [True, False])
            study.record_inputs(folder / 'results.json', {'policy': policy})
    fake_run(run, 8192, 6144, checkpoints=(5120, 6144), state=n)
    (run / 'events.out.tfevents.1.host').write_bytes(b'tb')


def _clone_plan():
    return study.StudyPlan(('smoke',), (0,), (4096, 8192), ('static', 'dynamic'),
                           {'smoke': 'ours'}, trials=2, dynamic_steps=2048, baselines=())


def _budget_tasks(tasks, n: int = 4096):
    return [t for t in tasks if t.key.startswith(f'smoke/seed0/{n}/')]


def test_done_by_content_survives_shuffled_times_and_missing_checkpoints(tmp_path):
    """A clone: file times arbitrary (every output older than its inputs) and no *.pt of a
    finished budget; its snapshot, policies and evaluations agree by sha256, so it is done."""
    import os

    layout, plan = study.Layout(tmp_path), _clone_plan()
    _budget_done(layout, plan)
    tasks = study.plan_tasks(layout, plan)
    done = _budget_tasks(tasks)
    assert len(done) == 1 + 1 + 2 + 4 and all(t.done() for t in done)
    for i, path in enumerate(sorted(tmp_path.rglob('*'))):
        if path.is_file():  # outputs (.onnx, results.json) before their inputs (.pt, .onnx)
            t = 2e9 - 2000 * (path.name == 'results.json') - 1000 * (path.suffix == '.onnx') + i
            os.utime(path, (t, t))
    assert not study.up_to_date(layout.policy('smoke', 0, 4096, 'static'),
                                layout.budget('smoke', 0, 4096) / 'best.pt')
    assert all(t.done() for t in done)
    for pt in tmp_path.rglob('*.pt'):
        pt.unlink()
    assert all(t.done() for t in done), [t.key for t in done if not t.done()]
    # what the clone does not have: the next budget (its training resumes; see the gitignore)
    assert not any(t.done() for t in _budget_tasks(tasks, 8192))


def test_a_changed_policy_or_checkpoint_is_not_done(tmp_path):
    layout, plan = study.Layout(tmp_path), _clone_plan()
    _budget_done(layout, plan)
    tasks = {t.key: t for t in study.plan_tasks(layout, plan)}
    key = 'smoke/seed0/4096'
    policy = layout.policy('smoke', 0, 4096, 'static')
    policy.write_bytes(b'another policy')  # re-exported: different bytes
    assert not tasks[f'{key}/eval-static-targets0'].done()
    assert not tasks[f'{key}/eval-static-targets1'].done()
    assert not tasks[f'{key}/export-static'].done()  # not the recorded output any more
    assert tasks[f'{key}/eval-dynamic-targets0'].done()
    # the dynamic run's best.pt changed: its export is stale; absent, the recorded hash holds
    best = layout.dynamic_run('smoke', 0, 4096) / 'best.pt'
    best.write_bytes(b'another best')
    assert not tasks[f'{key}/export-dynamic'].done()
    best.unlink()
    (best.parent / 'final.pt').unlink()
    assert tasks[f'{key}/export-dynamic'].done() and tasks[f'{key}/train-dynamic'].done()
    # a snapshot whose best.pt is not the one its static.onnx was exported from
    study.record_export(layout.budget('smoke', 0, 4096) / 'best.pt', policy)  # exported again
    assert tasks[f'{key}/export-static'].done()
    (layout.budget('smoke', 0, 4096) / 'best.pt').unlink()
    assert tasks[f'{key}/export-static'].done()  # by the snapshot's policy_sha256
    snap = layout.snapshot('smoke', 0, 4096)
    snap.write_text(json.dumps({**json.loads(snap.read_text()), 'policy_sha256': 'f' * 64}))
    assert tasks[f'{key}/train-static'].done() and not tasks[f'{key}/export-static'].done()


def test_outputs_made_before_records_go_by_file_times_then_are_recorded(tmp_path):
    import os

    policy, folder = tmp_path / 'static.onnx', tmp_path / 'eval'
    policy.write_bytes(b'onnx')
    write_results(folder, 'smoke', 'static', [True])
    os.utime(policy, (1_000, 1_000))
    assert study.made_from(folder / 'results.json', {'policy': policy}) is None
    assert study.evaluated(folder, policy, 1)
    assert study.adopt(folder / 'results.json', {'policy': policy})
    assert not study.adopt(folder / 'results.json', {'policy': policy})  # recorded once
    os.utime(policy, (4e9, 4e9))  # newer, same bytes: by content still current
    assert study.evaluated(folder, policy, 1)
    other = tmp_path / 'old' / 'results.json'
    write_results(other.parent, 'smoke', 'static', [True])
    os.utime(other, (1_000, 1_000))
    assert not study.adopt(other, {'policy': policy})  # older than its policy: not adopted


def _check_ignore(repo: Path, paths: list[str]) -> set[str]:
    import subprocess

    got = subprocess.run(['git', 'check-ignore', '--no-index', '--stdin'], cwd=repo,
                         input='\n'.join(paths) + '\n', capture_output=True, text=True,
                         check=False)
    assert got.returncode in (0, 1), got.stderr
    return set(got.stdout.split())


def test_the_gitignore_keeps_small_files_and_the_checkpoints_a_resume_needs(tmp_path):
    import subprocess

    repo = tmp_path / 'repo'
    subprocess.run(['git', 'init', '-q', str(repo)], check=True)
    layout, plan = study.Layout(repo / 'OUT'), _clone_plan()
    _budget_done(layout, plan)
    (repo / 'OUT' / '.lock').write_text('1\n')
    for name in ('report.md', 'summary.csv', 'results.csv', 'curves_ours_static.png'):
        (repo / 'OUT' / name).write_text('x')
    path = study.write_gitignore(layout.root, study.plan_tasks(layout, plan))
    assert path == repo / 'OUT' / '.gitignore'
    kept = ['report.md', 'summary.csv', 'results.csv', 'curves_ours_static.png', 'logs/x.log',
            'smoke/seed0/static/config.yaml', 'smoke/seed0/static/scalars.csv',
            'smoke/seed0/static/study_state.json',
            # the unfinished training: its latest checkpoint, final.pt and best.pt
            'smoke/seed0/static/checkpoints/step_6144.pt', 'smoke/seed0/static/final.pt',
            'smoke/seed0/static/best.pt',
            'smoke/seed0/steps_4096/snapshot.json', 'smoke/seed0/steps_4096/config.yaml',
            'smoke/seed0/steps_4096/static.onnx', 'smoke/seed0/steps_4096/static.onnx.sha256.json',
            'smoke/seed0/steps_4096/dynamic.onnx', 'smoke/seed0/steps_4096/dynamic/scalars.csv',
            'smoke/seed0/steps_4096/eval_static_targets1/results.json',
            'smoke/seed0/steps_4096/eval_static_targets1/results.json.sha256.json',
            'smoke/seed0/steps_4096/eval_dynamic_targets0/report.md']
    ignored = ['.lock', 'smoke/seed0/static/checkpoints/step_5120.pt',
               'smoke/seed0/static/events.out.tfevents.1.host',
               'smoke/seed0/static/checkpoints/step_7168.pt.tmp',
               'smoke/seed0/steps_4096/best.pt', 'smoke/seed0/steps_4096/dynamic/best.pt',
               'smoke/seed0/steps_4096/dynamic/final.pt',
               'smoke/seed0/steps_4096/dynamic/checkpoints/step_1024.pt']
    got = _check_ignore(repo, [f'OUT/{p}' for p in kept + ignored])
    assert got == {f'OUT/{p}' for p in ignored}
    # before the dynamic re-training is done the snapshot's best.pt (its --init-from) stays
    (layout.dynamic_run('smoke', 0, 4096) / 'study_state.json').unlink()
    study.write_gitignore(layout.root, study.plan_tasks(layout, plan))
    got = _check_ignore(repo, ['OUT/smoke/seed0/steps_4096/best.pt',
                               'OUT/smoke/seed0/steps_4096/dynamic/checkpoints/step_1024.pt',
                               'OUT/smoke/seed0/steps_4096/dynamic/final.pt'])
    assert got == set()


def test_gitignore_patterns_escape_special_characters():
    assert study.gitignore_pattern(Path('a b/[x]*?.pt')) == r'/a\ b/\[x\]\*\?.pt'
