"""What ``cgail session`` does around its trials (issue 34): the domain probe beside other work,
the bags evaluated as their trials end, the identification's cache check.

These change when the work is done, never its result: the report from bags evaluated on arrival
is the report from bags evaluated at the end, and the probe's check is the probe's check.
"""

from __future__ import annotations

from pathlib import Path
import shutil
import threading
from typing import Any

import pytest
import yaml

from cgail_rig import domain
from cgail_rig.session import evaluate_trial_bag, identification_cached, report

FIXTURES = Path(__file__).resolve().parents[4] / 'bags' / 'fixtures'


class _Lease:
    def __init__(self) -> None:
        self.domain_id = 7
        self.released = False
        self.thread = threading.current_thread().name

    def release(self) -> None:
        self.released = True


def test_the_domain_probe_runs_beside_the_work_and_returns_both(monkeypatch) -> None:
    leases: list[_Lease] = []

    def fake_reserve(**_: object) -> _Lease:
        leases.append(_Lease())
        return leases[-1]

    monkeypatch.setattr(domain, 'reserve_domain', fake_reserve)
    lease, value = domain.reserve_domain_during(lambda: threading.current_thread().name)
    assert value == threading.current_thread().name  # the work runs in this thread
    assert lease is leases[0]  # type: ignore[comparison-overlap]
    assert leases[0].thread != value  # the probe in another
    assert not leases[0].released


def test_a_failing_work_releases_the_domain_and_raises(monkeypatch) -> None:
    leases: list[_Lease] = []

    def fake_reserve(**_: object) -> _Lease:
        leases.append(_Lease())
        return leases[-1]

    def work() -> None:
        raise ValueError('no such module')

    monkeypatch.setattr(domain, 'reserve_domain', fake_reserve)
    with pytest.raises(ValueError, match='no such module'):
        domain.reserve_domain_during(work)
    assert leases[0].released


def test_a_refused_domain_is_raised_after_the_work(monkeypatch) -> None:
    done: list[bool] = []

    def refuse(**_: object) -> None:
        raise domain.DomainError('device node aurora answers')

    monkeypatch.setattr(domain, 'reserve_domain', refuse)
    with pytest.raises(domain.DomainError, match='aurora'):
        domain.reserve_domain_during(lambda: done.append(True))
    assert done == [True]


def _bags(root: Path) -> Path:
    bags = root / 'bags'
    for condition in ('cgail', 'centerline'):
        (bags / condition).mkdir(parents=True)
        shutil.copytree(FIXTURES / f'{condition}_trial', bags / condition / f'{condition}_01')
    return bags


def test_bags_evaluated_as_they_came_give_the_same_report(tmp_path) -> None:
    outcomes = [('cgail', 1, 'at the target (1.0 mm)'), ('centerline', 1, 'time limit')]
    bags = _bags(tmp_path / 'run')
    printed: list[list[str]] = [[], []]
    assert report(tmp_path / 'end', bags, outcomes, printed[0].append, wall_s=1.0) == 0
    evaluated = {(b.parent.name, b.name): evaluate_trial_bag(b) for b in bags.glob('*/*')}
    assert all(metrics and not why for metrics, why in evaluated.values())
    assert report(tmp_path / 'arrival', bags, outcomes, printed[1].append, wall_s=1.0,
                  evaluated=evaluated) == 0
    assert (tmp_path / 'end' / 'metrics.md').read_text() == \
        (tmp_path / 'arrival' / 'metrics.md').read_text()
    assert (tmp_path / 'end' / 'metrics.csv').read_text() == \
        (tmp_path / 'arrival' / 'metrics.csv').read_text()
    assert printed[0][:-1] == printed[1][:-1]  # (the last line names the output directory)


def test_the_report_uses_what_was_evaluated_on_arrival(tmp_path) -> None:
    bags = _bags(tmp_path)
    evaluated: dict[tuple[str, str], tuple[list[Any], str]] = {
        ('centerline', 'centerline_01'): ([], 'expected a path, found none')}
    assert report(tmp_path, bags, [('cgail', 1, 'x'), ('centerline', 1, 'y')], lambda _: None,
                  wall_s=1.0, evaluated=evaluated) == 0
    text = (tmp_path / 'metrics.md').read_text()
    assert '- centerline_01: expected a path, found none' in text


def test_a_missing_bag_has_no_metrics_and_says_why(tmp_path) -> None:
    metrics, why = evaluate_trial_bag(tmp_path / 'cgail' / 'cgail_01')
    assert metrics == [] and 'cgail_01' in why


def test_identification_cached_needs_every_identified_key(tmp_path) -> None:
    from pam_controller.core.identification import IDENTIFIED_KEYS

    assert not identification_cached(tmp_path, 0)
    path = tmp_path / 'plant_seed_0' / 'pam_identified.yaml'
    path.parent.mkdir()
    values = {key: 0.5 for key in IDENTIFIED_KEYS}
    path.write_text(yaml.safe_dump({'pam_controller': {'ros__parameters': values}}))
    assert identification_cached(tmp_path, 0)
    assert not identification_cached(tmp_path, 1)
    del values[IDENTIFIED_KEYS[0]]
    path.write_text(yaml.safe_dump({'pam_controller': {'ros__parameters': values}}))
    assert not identification_cached(tmp_path, 0)


def test_the_fit_runs_blas_on_one_thread_and_restores_it() -> None:
    """The identification's fit (:func:`cgail_rig.identify_pam.one_blas_thread`): one thread in
    the block, each OpenBLAS's own count after it; the results of numpy within are numpy's."""
    import ctypes

    import numpy as np

    from cgail_rig.identify_pam import _OPENBLAS_THREADS, one_blas_thread

    def counts() -> list[int]:
        found = []
        maps = Path('/proc/self/maps').read_text().splitlines()
        for path in sorted({line.split()[-1] for line in maps
                            if 'openblas' in line.rsplit('/', 1)[-1] and '.so' in line}):
            lib = ctypes.CDLL(path)
            for get, _ in _OPENBLAS_THREADS:
                if hasattr(lib, get):
                    found.append(int(getattr(lib, get)()))
                    break
        return found

    if not Path('/proc/self/maps').is_file():
        pytest.skip('expected /proc/self/maps (Linux), found none')
    a = np.arange(36.0).reshape(6, 6)
    before = counts()
    with one_blas_thread():
        inside = counts()
        product = a @ a
    assert inside == [1] * len(before)
    assert counts() == before
    assert np.array_equal(product, a @ a)
