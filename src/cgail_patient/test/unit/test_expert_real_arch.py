"""The scripted expert through a real, tight aortic arch (AVT D11, shipped as ``avt-D11``).

D11's arch is about as tight as the catheter's smallest bend radius (31.8 mm): a tip that
reaches its apex on the wrong line cannot turn in time, 50-60 mm after the choice that put it
there. The expert that scored only the next 16 mm reached none of D11's standard targets in
the rigid aorta (every episode a collision at the arch's outer wall); pursuit first with the
64 mm horizon reaches them (cgail_learning/expert.py).
"""

from __future__ import annotations

import pytest

from cgail_learning.expert import ScriptedExpert
from cgail_patient.validate import run_expert_trial
from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv

REAL_D11 = "avt-D11"


@pytest.fixture(scope="module")
def d11_env() -> CatheterNavEnv:
    return CatheterNavEnv(EnvConfig(mode="static", anatomy=REAL_D11,
                                    scenario_seed=0))


@pytest.mark.parametrize("start, target", [(1, 1), (2, 4)])
def test_expert_passes_the_tight_real_arch(d11_env, start, target) -> None:
    trial = run_expert_trial(d11_env, ScriptedExpert(d11_env), start, target)
    assert trial.outcome == "success", trial.detail
    assert trial.contact_steps == 0
