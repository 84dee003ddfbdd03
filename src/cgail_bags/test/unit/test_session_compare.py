"""``session_compare``: metrics.csv read back exactly, sessions side by side, one-line errors."""

import math
from pathlib import Path

import pytest

from cgail_bags.compare_cli import main, parse_session
from cgail_bags.report import read_csv, session_comparison, write_csv
from cgail_planner.core.metrics import MetricsError, TrialMetrics


def metrics(name: str, condition: str, t_r_mm: float, t_a_mm: float,
            success: bool = True) -> TrialMetrics:
    return TrialMetrics(name=name, condition=condition, samples=100,
                        tracking_mean=t_r_mm * 1e-3, tracking_std=0.5e-3,
                        tracking_max=2 * t_r_mm * 1e-3, targeting_error=t_a_mm * 1e-3,
                        duration=80.0, success=success,
                        time_to_target=70.0 if success else math.nan, timed_out=not success,
                        curvature_mean=2500.0, curvature_std=900.0, path_length=0.25)


def session(tmp_path: Path, name: str, cgail: list[float], centerline: list[float]) -> Path:
    trials = [metrics(f'cgail_{i:02d}', 'cgail', v, v) for i, v in enumerate(cgail, 1)]
    trials += [metrics(f'centerline_{i:02d}', 'centerline', v, 2 * v, success=i > 1)
               for i, v in enumerate(centerline, 1)]
    write_csv(trials, tmp_path / name / 'metrics.csv')
    return tmp_path / name


def test_metrics_csv_reads_back_what_was_written(tmp_path) -> None:
    trials = [metrics('a', 'cgail', 1.25, 3.5), metrics('b', 'centerline', 4.0, 2.0, False)]
    path = write_csv(trials, tmp_path / 'metrics.csv')
    back = read_csv(path)
    assert [t.name for t in back] == ['a', 'b']
    for mine, theirs in zip(trials, back, strict=True):
        for field in ('samples', 'tracking_mean', 'targeting_error', 'success', 'timed_out'):
            assert getattr(theirs, field) == getattr(mine, field)
        assert type(theirs.samples) is int and type(theirs.success) is bool
    assert math.isnan(back[1].time_to_target)


def test_sessions_side_by_side_with_improvement_p_and_effect_size(tmp_path) -> None:
    one = session(tmp_path, 'one', [1.0, 1.1, 1.2, 1.3, 1.4], [2.0, 2.1, 2.2, 2.3, 2.4])
    two = session(tmp_path, 'two', [2.0, 2.1, 2.2], [2.0, 2.1, 2.2])
    text = session_comparison({'A': read_csv(one / 'metrics.csv'),
                               'B': read_csv(two / 'metrics.csv')})
    rows = {tuple(c.strip() for c in line.strip('|').split('|')[:2]): line
            for line in text.splitlines() if line.startswith('| ')}
    assert '| 5 | 100% [57%-100%] | 1.20 ± 0.16' in rows[('A', 'cgail')]
    assert '| 5 | 80% [38%-96%] | 2.20 ± 0.16' in rows[('A', 'centerline')]
    # A: every C-GAIL trial below every centerline one: delta -1, T_r 45 % better
    a = next(line for line in text.splitlines() if line.startswith('| A | 45%'))
    cells = [c.strip() for c in a.strip('|').split('|')]
    assert float(cells[2]) < 0.05 and cells[3] == '-1.00 (large)'
    # B: identical T_r samples: no improvement, delta 0; T_a of the centerline twice
    b = next(line for line in text.splitlines() if line.startswith('| B | 0%'))
    cells = [c.strip() for c in b.strip('|').split('|')]
    assert cells[3] == '0.00 (negligible)' and cells[4] == '50%'
    assert '| paper (in vitro) | cgail | 10 | 100% | 5.18 ± 3.48 | 1.26 ± 0.55 |' in text


def test_the_command_writes_the_table_and_the_plot(tmp_path, capsys) -> None:
    one = session(tmp_path, 'one', [1.0, 1.2, 1.4], [2.0, 2.2, 2.4])
    two = session(tmp_path, 'two', [1.5, 1.7, 1.9], [1.6, 1.8, 2.0])
    out = tmp_path / 'cmp'
    assert main([f'static={one}', str(two), '-o', str(out)]) == 0
    text = (out / 'compare.md').read_text()
    assert '| static | cgail | 3 |' in text and '| two | centerline | 3 |' in text
    assert (out / 'compare_boxplot.png').stat().st_size > 10_000
    assert 'wrote' in capsys.readouterr().out


@pytest.mark.parametrize('content, expected', [
    (None, 'expected a metrics.csv (cgail session / cgail bag metrics output), found no file'),
    ('', 'expected the header name,condition,samples'),
    ('name,condition\nx,y\n', 'expected the header'),
    ('HEADER\ncgail_01,cgail,ten,0.001,0.001,0.002,0.001,80,True,70,False,1,1,0.2\n',
     ':2: expected samples to be int, found \'ten\''),
    ('HEADER\ncgail_01,cgail,10,0.001,0.001,0.002,0.001,80,yes,70,False,1,1,0.2\n',
     ':2: expected success to be bool, found \'yes\''),
    ('HEADER\ncgail_01,cgail,10\n', ':2: expected 14 fields, found 3'),
    ('HEADER\n', 'expected at least one trial, found none'),
])
def test_a_bad_metrics_csv_is_one_line_and_exit_status_2(tmp_path, capsys, content,
                                                         expected) -> None:
    where = tmp_path / 's'
    where.mkdir()
    if content is not None:
        header = ('name,condition,samples,tracking_mean,tracking_std,tracking_max,'
                  'targeting_error,duration,success,time_to_target,timed_out,curvature_mean,'
                  'curvature_std,path_length')
        (where / 'metrics.csv').write_text(content.replace('HEADER', header))
    assert main([str(where), '-o', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith('cgail bag compare: error: ')
    assert expected in err


def test_labels_must_be_distinct_and_well_formed(tmp_path, capsys) -> None:
    one = session(tmp_path, 'one', [1.0, 1.2], [2.0, 2.2])
    assert parse_session(f'x={one}') == ('x', one)
    assert parse_session(str(one)) == ('one', one)
    with pytest.raises(MetricsError, match="expected LABEL=DIR or DIR"):
        parse_session(f'={one}')
    assert main([f'x={one}', f'x={one}', '-o', str(tmp_path / 'out')]) == 2
    assert "session label 'x' given twice" in capsys.readouterr().err


def test_a_tiny_p_value_is_written_in_scientific_notation_not_as_zero(tmp_path) -> None:
    lo = [1.0 + 0.01 * i for i in range(30)]
    hi = [2.0 + 0.01 * i for i in range(30)]
    text = session_comparison({'S': read_csv(session(tmp_path, 's', lo, hi) / 'metrics.csv')})
    row = [line for line in text.splitlines() if line.startswith('| S | ')][-1]  # C-GAIL vs
    p = [c.strip() for c in row.strip('|').split('|')][2]                          # centerline
    assert 'e-' in p and 0.0 < float(p) < 1e-3
