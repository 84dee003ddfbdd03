"""Cross-check: the `imitation` library's GAIL and BC on our env and our 70 demonstrations.

Run (any Python >= 3.10; the script builds and reuses its own virtual environment)::

    python bench/crosscheck_imitation.py --variant standard --steps 2000000 --seeds 0 1
    python bench/crosscheck_imitation.py --variant shifted --steps 2000000 --seeds 0 1
    python bench/crosscheck_imitation.py --variant bc --seeds 0
    python bench/crosscheck_imitation.py --variant standard --seeds 0 --resume   # continue

Issue 13 ran GAIL from ``imitation`` 1.0.1 on stable-baselines3 2.2.1 PPO against this env and
its demonstrations; this script re-runs that check so anyone can repeat it. It first builds a
virtual environment (default ``runs/crosscheck_imitation/.venv``, reused when present) with
``python -m venv`` and pip: ``imitation==1.0.1``, ``stable-baselines3==2.2.1``,
``gymnasium==0.29.1`` (imitation needs 0.29; the workspace runs 1.x), ``torch==2.13.0`` (the
CPU wheel; a bare ``torch`` pulls GBs of CUDA) and the packages ``cgail_sim``, the demo
loader and ``evaluate`` import, at the versions ``requirements.txt`` pins. Our package is not
installed: ``src/cgail_planner`` goes on ``PYTHONPATH``. pip needs PyPI (or the index the usual
``PIP_*`` variables name). The script then re-executes itself inside that environment.

What runs, per seed:

* **env**: ``CatheterNavEnv(EnvConfig(mode='static'))``, the default anatomy, 8 copies in an SB3
  ``DummyVecEnv`` (each under SB3's ``Monitor``); start and target drawn per episode.
* **demonstrations**: ``bags/demos/default`` (docs/tutorials/demonstrations.md) through our own
  :func:`cgail_learning.demos.load_demos`, so the (obs, act) pairs are the ones ``train``
  uses; episode ends from the bag's episode headers. They become ``imitation`` ``Transitions``;
  an episode's last ``next_obs`` repeats its last ``obs`` (the bag does not hold the terminal
  observation, and the discriminator here does not read ``next_obs``).
* **PPO** (SB3), the ML-Agents settings of our presets (those of the ``gail`` preset until
  2026-12-02, ``bench/gail_variants/gail_ml_agents.yaml``): 2 x 64 SiLU layers for policy and
  value, initial log std -1.0, lr 3e-4 (constant, so a resumed run continues the same schedule),
  ``n_steps`` 1280 x 8 envs = 10,240 steps a round, minibatch 1024, 3 epochs, gamma 0.99,
  GAE lambda 0.95, clip 0.2, entropy coefficient 5e-4; no observation normalisation (ours is
  pre-scaled).
* **GAIL** (``imitation.algorithms.adversarial.gail.GAIL``): discriminator
  ``BasicRewardNet`` on the observation only (as ML-Agents' ``use_actions: false`` and our
  preset; ``--disc-actions`` adds the action), 2 x 64 hidden units, input ``RunningNorm``;
  Adam lr 3e-4; 4 discriminator updates a round on 1024 demo + 1024 policy samples; variable
  horizon allowed (our episodes end on success, collision or exit).
  * ``standard``: imitation's reward ``-log(1 - D)`` (never negative).
  * ``shifted``: ``-log(1 - D) - log 2``, this project's GAIL reward until 2026-12 (negative
    whenever the discriminator tells the policy apart), applied by a wrapper around the
    discriminator's reward.
* ``--ppo sb3`` replaces our preset's PPO settings by SB3's own defaults (``ppo_kwargs``);
  with ``--disc-actions`` that is imitation's and SB3's out-of-the-box GAIL. The run folder
  name says which (``standard_sb3ppo_disc_actions_seed0``).
* **bc**: ``imitation.algorithms.bc.BC`` alone, its default policy (2 x 32) and settings,
  5 epochs (``--bc-epochs``) over the same transitions; no env steps.

**Evaluation**: the deterministic policy (mean action) over 30 episodes through our own
:func:`cgail_learning.evaluate.run_trials`: trial k uses start ``k % 3``, target
``(k // 3) % 5``, seed ``1000 + k``, no tracking noise; in the static noise-free simulator a
deterministic policy's outcome is a function of the pair, so each of the 15 pairs is simulated
once and counted twice (``reuse_pairs``, as ``evaluate`` does). Printed per run: success k/30
and mean episode length (steps).

**Output**: each run lives in ``<root>/<variant>_seed<seed>/`` (``--root``, default
``runs/crosscheck_imitation``): ``ppo.zip`` + ``disc.pt`` + ``state.json`` (checkpoint every
``--checkpoint-every`` steps and at the end), ``curve.csv`` (per round: steps, wall time,
training-episode success and length) and ``result.json``. ``--out`` (default
``<root>/report.md``) gets a markdown table of every finished run under the root and
``curve.png`` (training success and episode length against steps). A progress line per round
shows the steps, elapsed time, steps/s and the ETA. ``--resume`` continues a run from its
checkpoint up to ``--steps`` (the discriminator's replay buffer and the random streams restart,
so a resumed run is a continuation, not a bit-identical replay).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from pathlib import Path
import re
import subprocess
import sys
import time
from typing import Any

WS = Path(__file__).resolve().parent.parent
#: The packages it imports (learning and the packages below it), put on the path from source.
PKG_PATHS = [WS / 'src' / p
             for p in ('cgail_sim', 'cgail_planner', 'cgail_bags', 'cgail_learning')]
DEMOS = WS / 'bags' / 'demos' / 'default'

#: Pinned here: the cross-check's own stack (issue 13).
PINNED = {'imitation': '1.0.1', 'stable-baselines3': '2.2.1', 'gymnasium': '0.29.1',
          'torch': '2.13.0'}
#: Pinned by requirements.txt: what ``cgail_sim``, ``learning.demos``/``demo_bags`` and
#: ``learning.evaluate`` import (numba kernels, trimesh meshes, rosbags + zstd demo bags,
#: onnxruntime through ``evaluate``'s ``OnnxPolicy`` import, matplotlib for the curve).
FROM_REQUIREMENTS = ('numpy', 'scipy', 'numba', 'trimesh', 'embreex', 'rtree', 'networkx',
                     'rosbags', 'zstandard', 'PyYAML', 'matplotlib', 'onnxruntime', 'tqdm')

VARIANTS = ('standard', 'shifted', 'bc')
EVAL_TRIALS, EVAL_SEED = 30, 1000
N_ENVS, N_STEPS = 8, 1280


class CrosscheckError(RuntimeError):
    """A one-line failure of the cross-check (printed without a traceback)."""


# ------------------------------------------------------------------------------------------
# Outside the venv: build it, then re-execute inside it (standard library only).


def requirement_pins(requirements: Path = WS / 'requirements.txt') -> list[str]:
    """``name==version`` for every package the venv needs, in install order."""
    pins = {}
    for line in requirements.read_text().splitlines():
        m = re.match(r'^([A-Za-z0-9_.-]+)(?:\[[^\]]*\])?==([^\s#;]+)', line.strip())
        if m:
            pins[m.group(1).lower()] = m.group(2)
    out = []
    for name in FROM_REQUIREMENTS:
        if name.lower() not in pins:
            raise CrosscheckError(f'expected a pin for {name} in {requirements}, found none')
        out.append(f'{name}=={pins[name.lower()]}')
    return out + [f'{name}=={version}' for name, version in PINNED.items()]


def venv_python(venv: Path) -> Path:
    """The interpreter of ``venv``."""
    return venv / ('Scripts/python.exe' if os.name == 'nt' else 'bin/python')


def failed_package(pip_output: str) -> str | None:
    """The requirement pip names as the one it could not get, if it names one."""
    for pattern in (r'No matching distribution found for (\S+)',
                    r'Could not find a version that satisfies the requirement (\S+)',
                    r'ERROR: Could not install packages .*?(\S+==\S+)',
                    r'Cannot install (\S+==\S+)'):
        m = re.search(pattern, pip_output)
        if m:
            return m.group(1)
    return None


def ensure_venv(venv: Path) -> None:
    """Create ``venv`` and install the pins when it is missing or its pins changed."""
    pins = requirement_pins()
    want = hashlib.sha256('\n'.join(pins).encode()).hexdigest()
    stamp = venv / '.crosscheck.sha256'
    py = venv_python(venv)
    if py.exists() and stamp.exists() and stamp.read_text().strip() == want:
        print(f'crosscheck: reusing {venv}', flush=True)
        return
    t0 = time.monotonic()
    if not py.exists():
        print(f'crosscheck: creating {venv} with Python {sys.version.split()[0]}', flush=True)
        venv.parent.mkdir(parents=True, exist_ok=True)
        proc = subprocess.run([sys.executable, '-m', 'venv', str(venv)],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or ['(no output)'])[-1]
            raise CrosscheckError(f'python -m venv {venv} failed: {last} (Debian: apt-get '
                                  'install python3-venv)')
    print(f'crosscheck: installing {len(pins)} pinned packages into {venv} (first time: a few '
          'minutes): ' + ' '.join(pins), flush=True)
    log = venv.parent / 'pip.log'
    proc = subprocess.run([str(py), '-m', 'pip', 'install', '--disable-pip-version-check',
                           *pins], capture_output=True, text=True)
    log.write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        pkg = failed_package(proc.stdout + proc.stderr)
        what = f'could not install {pkg}' if pkg else 'failed'
        raise CrosscheckError(f'pip {what}: PyPI (or the index PIP_INDEX_URL names) must be '
                              f'reachable to build {venv}; full output in {log}')
    stamp.write_text(want + '\n')
    print(f'crosscheck: venv ready in {time.monotonic() - t0:.0f} s', flush=True)


def reexec_in_venv(venv: Path, argv: list[str]) -> None:
    """Replace this process by the script running in ``venv`` with our package importable."""
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(
        [str(p) for p in PKG_PATHS] + ([env['PYTHONPATH']] if env.get('PYTHONPATH') else []))
    env.setdefault('OMP_NUM_THREADS', '1')
    env.setdefault('TQDM_DISABLE', '1')  # imitation's per-round bar: our progress lines instead
    py = str(venv_python(venv))
    os.execve(py, [py, str(Path(__file__).resolve()), *argv], env)


def in_venv(venv: Path) -> bool:
    """Whether this interpreter is the one of ``venv``."""
    return Path(sys.prefix).resolve() == venv.resolve()


# ------------------------------------------------------------------------------------------
# Inside the venv: the cross-check itself. The imports of imitation, stable-baselines3 and
# torch live in the functions: the workspace's own environment (ruff, mypy) does not have them.


def load_transitions(demos: Path) -> Any:
    """Our demonstrations (``load_demos``, the pairs ``train`` uses) as imitation Transitions."""
    from imitation.data.types import Transitions  # type: ignore[import-not-found]
    import numpy as np

    from cgail_learning.demo_bags import read_demo_bag
    from cgail_learning.demos import load_demos

    data = load_demos([demos], report=lambda line: print(f'crosscheck: demonstrations: {line}'))
    n = len(data.obs)
    _, episodes = read_demo_bag(demos)
    lengths = [len(ep.alpha) for ep in episodes if ep.success]
    dones = np.zeros(n, dtype=bool)
    if sum(lengths) == n:
        dones[np.cumsum(lengths) - 1] = True
    else:  # an episode re-simulated to an earlier end: its boundary is not known here
        print(f'crosscheck: note: the bag\'s episodes hold {sum(lengths)} steps, the replay '
              f'{n}; episode ends are not marked (the discriminator does not read them)')
        dones[-1] = True
    next_obs = np.concatenate([data.obs[1:], data.obs[-1:]])
    next_obs[dones] = data.obs[dones]  # no terminal observation in the bag
    print(f'crosscheck: {n} demonstration pairs from {int(dones.sum())} episodes ({demos})')
    return Transitions(obs=data.obs, acts=data.act, infos=np.array([{}] * n),
                       next_obs=next_obs, dones=dones)


def make_env() -> Any:
    """Our env: default anatomy, static (rigid) wall."""
    from cgail_sim.config import EnvConfig
    from cgail_sim.env import CatheterNavEnv

    return CatheterNavEnv(EnvConfig(mode='static'))


def make_training_venv(seed: int) -> tuple[Any, list[tuple[bool, int]]]:
    """``N_ENVS`` monitored copies of our env, and the list the finished episodes go to."""
    from stable_baselines3.common.monitor import Monitor  # type: ignore[import-not-found]
    from stable_baselines3.common.vec_env import (  # type: ignore[import-not-found]
        DummyVecEnv,
        VecEnvWrapper,
    )

    finished: list[tuple[bool, int]] = []

    class EpisodeLog(VecEnvWrapper):  # type: ignore[misc]
        """Records (success, length) of every training episode that ends."""

        def reset(self) -> Any:
            return self.venv.reset()

        def step_wait(self) -> Any:
            obs, rews, dones, infos = self.venv.step_wait()
            for done, info in zip(dones, infos, strict=True):
                if done:
                    finished.append((bool(info.get('is_success', False)),
                                     int(info['episode']['l'])))
            return obs, rews, dones, infos

    venv = EpisodeLog(DummyVecEnv([lambda: Monitor(make_env())] * N_ENVS))
    venv.seed(seed)
    return venv, finished


def ppo_kwargs(settings: str = 'ours') -> dict[str, Any]:
    """SB3 PPO settings: ``ours``, ML-Agents' as in ``gail_ml_agents.yaml`` (module
    docstring); ``sb3``, SB3 2.2.1's own defaults (lr 3e-4, ``n_steps`` 2048 per env,
    minibatch 64, 10 epochs, gamma 0.99, GAE lambda 0.95, clip 0.2, no entropy bonus, 2 x 64
    tanh, initial log std 0)."""
    import torch

    if settings == 'sb3':
        return {}
    return dict(learning_rate=3e-4, n_steps=N_STEPS, batch_size=1024, n_epochs=3, gamma=0.99,
                gae_lambda=0.95, clip_range=0.2, ent_coef=5e-4, vf_coef=0.5,
                policy_kwargs=dict(net_arch=dict(pi=[64, 64], vf=[64, 64]),
                                   activation_fn=torch.nn.SiLU, log_std_init=-1.0))


def gail_kwargs(disc_actions: bool) -> dict[str, Any]:
    """imitation GAIL and discriminator settings (see the module docstring)."""
    return dict(demo_batch_size=1024, n_disc_updates_per_round=4,
                disc_opt_kwargs=dict(lr=3e-4), allow_variable_horizon=True,
                disc_hidden=(64, 64), disc_actions=disc_actions)


def evaluate(policy: Any) -> dict[str, float]:
    """Deterministic policy over ``EVAL_TRIALS`` episodes with our ``evaluate.run_trials``."""
    import numpy as np

    from cgail_learning.evaluate import run_trials

    def act(obs: Any) -> Any:
        return policy.predict(obs, deterministic=True)[0]

    trials = run_trials(make_env(), act, EVAL_TRIALS, EVAL_SEED, reuse_pairs=True)
    return {'success': sum(t.success for t in trials), 'episodes': len(trials),
            'collisions': sum(t.collision for t in trials),
            'mean_length': float(np.mean([t.timesteps for t in trials]))}


def save_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` to ``path`` atomically."""
    tmp = path.with_suffix(path.suffix + '.tmp')
    tmp.write_text(json.dumps(data, indent=1) + '\n')
    tmp.replace(path)


def gail_trainer_class(variant: str) -> Any:
    """imitation's ``GAIL`` for ``standard``; for ``shifted``, a subclass that pays the policy
    ``-log(1 - D) - log 2`` through a wrapper around imitation's reward (the discriminator and
    its loss are unchanged)."""
    import math

    from imitation.algorithms.adversarial.gail import GAIL  # type: ignore[import-not-found]
    from imitation.rewards.reward_nets import RewardNet  # type: ignore[import-not-found]

    if variant == 'standard':
        return GAIL

    class ShiftedReward(RewardNet):  # type: ignore[misc]
        """``base - log 2``."""

        def __init__(self, base: Any) -> None:
            super().__init__(base.observation_space, base.action_space,
                             normalize_images=base.normalize_images)
            self.base = base

        def forward(self, state: Any, action: Any, next_state: Any, done: Any) -> Any:
            return self.base(state, action, next_state, done) - math.log(2.0)

    class ShiftedGAIL(GAIL):  # type: ignore[misc]
        """GAIL whose training reward (the one its reward wrapper pays) is shifted by -log 2."""

        _shifted: Any = None

        @property
        def reward_train(self) -> Any:
            # (read once by the trainer's constructor, which binds it into the reward wrapper)
            if self._shifted is None:
                self._shifted = ShiftedReward(self._processed_reward)
            return self._shifted

    return ShiftedGAIL

def run_gail(args: argparse.Namespace, seed: int, run_dir: Path, demos: Any) -> dict[str, Any]:
    """Train (or continue) one GAIL run; returns its result."""
    import math

    from imitation.rewards.reward_nets import BasicRewardNet  # type: ignore[import-not-found]
    from imitation.util import logger as imit_logger  # type: ignore[import-not-found]
    from imitation.util.networks import RunningNorm  # type: ignore[import-not-found]
    from stable_baselines3 import PPO  # type: ignore[import-not-found]
    import torch

    name = f'{args.variant} seed {seed}'
    state_path, ppo_path, disc_path = (run_dir / 'state.json', run_dir / 'ppo.zip',
                                       run_dir / 'disc.pt')
    state: dict[str, Any] = {'variant': args.variant, 'seed': seed, 'steps': 0,
                             'elapsed_s': 0.0}
    if state_path.exists():
        old = json.loads(state_path.read_text())
        if not args.resume:
            raise CrosscheckError(f'{run_dir} holds a checkpoint at {old["steps"]:,} steps: pass '
                                  '--resume to continue it, or delete the folder to start over')
        state = old
    elif args.resume:
        print(f'crosscheck: {name}: no checkpoint in {run_dir}; starting from scratch')
    run_dir.mkdir(parents=True, exist_ok=True)
    venv, finished = make_training_venv(seed + 1000 * int(state['steps'] > 0))
    g = gail_kwargs(args.disc_actions)
    if state['steps'] > 0:
        model = PPO.load(ppo_path, env=venv, device='cpu')
        print(f'crosscheck: {name}: resumed from {ppo_path} at {model.num_timesteps:,} steps')
    else:
        model = PPO('MlpPolicy', venv, seed=seed, device='cpu', verbose=0,
                    **ppo_kwargs(args.ppo))
    reward_net = BasicRewardNet(venv.observation_space, venv.action_space,
                                use_action=g['disc_actions'], hid_sizes=g['disc_hidden'],
                                normalize_input_layer=RunningNorm)
    trainer_cls = gail_trainer_class(args.variant)
    trainer = trainer_cls(
        demonstrations=demos, demo_batch_size=g['demo_batch_size'], venv=venv,
        gen_algo=model, reward_net=reward_net,
        n_disc_updates_per_round=g['n_disc_updates_per_round'],
        disc_opt_kwargs=g['disc_opt_kwargs'], allow_variable_horizon=g['allow_variable_horizon'],
        custom_logger=imit_logger.configure(
            run_dir / 'imitation_log' / f'from_{model.num_timesteps}', ['csv']))
    if state['steps'] > 0:
        saved = torch.load(disc_path, weights_only=True)
        reward_net.load_state_dict(saved['reward_net'])
        trainer._disc_opt.load_state_dict(saved['disc_opt'])
    per_round = trainer.gen_train_timesteps
    rounds = max(0, math.ceil((args.steps - model.num_timesteps) / per_round))
    t0, elapsed0 = time.monotonic(), float(state['elapsed_s'])
    last_ckpt = model.num_timesteps
    curve = run_dir / 'curve.csv'
    if not curve.exists() or state['steps'] == 0:
        curve.write_text('steps,elapsed_s,train_episodes,train_success,train_length\n')

    def checkpoint() -> None:
        model.save(ppo_path)
        torch.save({'reward_net': reward_net.state_dict(),
                    'disc_opt': trainer._disc_opt.state_dict()}, disc_path)
        state.update(steps=int(model.num_timesteps),
                     elapsed_s=elapsed0 + time.monotonic() - t0)
        save_json(state_path, state)

    def on_round(_: int) -> None:
        nonlocal last_ckpt
        steps = int(model.num_timesteps)
        elapsed = elapsed0 + time.monotonic() - t0
        eps = list(finished)
        finished.clear()
        succ = sum(s for s, _ in eps) / len(eps) if eps else float('nan')
        length = sum(n for _, n in eps) / len(eps) if eps else float('nan')
        with curve.open('a') as f:
            f.write(f'{steps},{elapsed:.1f},{len(eps)},{succ:.4f},{length:.1f}\n')
        rate = (steps - last_start) / max(time.monotonic() - t0, 1e-9)
        eta = (args.steps - steps) / rate if rate > 0 else float('nan')
        episodes = (f'training episodes {len(eps)}: success {100 * succ:.0f}%, mean length '
                    f'{length:.0f}' if eps else 'no training episode ended this round')
        print(f'[{name}] {steps:,}/{args.steps:,} steps, {elapsed:.0f} s, {rate:.0f} steps/s, '
              f'ETA {max(eta, 0) / 60:.1f} min | {episodes}', flush=True)
        if steps - last_ckpt >= args.checkpoint_every:
            checkpoint()
            last_ckpt = steps

    last_start = model.num_timesteps
    print(f'crosscheck: {name}: {rounds} rounds of {per_round:,} steps to reach '
          f'{args.steps:,} (checkpoint every {args.checkpoint_every:,} steps in {run_dir})',
          flush=True)
    if rounds > 0:
        trainer.train(rounds * per_round, callback=on_round)
    checkpoint()
    train_s = time.monotonic() - t0
    t_eval = time.monotonic()
    ev = evaluate(model)
    print(f'crosscheck: {name}: evaluation {time.monotonic() - t_eval:.0f} s')
    return {'variant': args.variant, 'seed': seed, 'steps': int(model.num_timesteps),
            'train_wall_s': round(float(state['elapsed_s']), 1),
            'steps_per_s': round((model.num_timesteps - last_start) / max(train_s, 1e-9), 1),
            **ev}


def run_bc(args: argparse.Namespace, seed: int, run_dir: Path, demos: Any) -> dict[str, Any]:
    """imitation BC alone on the demonstrations; returns its result."""
    from imitation.algorithms.bc import BC  # type: ignore[import-not-found]
    from imitation.util import logger as imit_logger  # type: ignore[import-not-found]
    import numpy as np
    from stable_baselines3.common.utils import set_random_seed  # type: ignore[import-not-found]

    set_random_seed(seed)
    env = make_env()
    run_dir.mkdir(parents=True, exist_ok=True)
    bc = BC(observation_space=env.observation_space, action_space=env.action_space,
            rng=np.random.default_rng(seed), demonstrations=demos, device='cpu',
            custom_logger=imit_logger.configure(run_dir / 'imitation_log', ['csv']))
    t0 = time.monotonic()
    bc.train(n_epochs=args.bc_epochs, progress_bar=False)
    train_s = time.monotonic() - t0
    bc.policy.save(run_dir / 'bc_policy.zip')
    print(f'crosscheck: bc seed {seed}: {args.bc_epochs} epochs in {train_s:.0f} s')
    return {'variant': 'bc', 'seed': seed, 'steps': 0, 'bc_epochs': args.bc_epochs,
            'train_wall_s': round(train_s, 1), 'steps_per_s': None, **evaluate(bc.policy)}


def write_report(root: Path, out: Path) -> None:
    """Markdown table of every finished run under ``root``, and the learning curves."""
    results = [json.loads(p.read_text()) for p in sorted(root.glob('*/result.json'))]
    results.sort(key=lambda r: (VARIANTS.index(r['variant']), r['steps'], r['seed']))
    lines = ['# imitation cross-check (bench/crosscheck_imitation.py)', '',
             'Our static env (default anatomy) and the 70 committed demonstrations, trained with '
             'the `imitation` library; deterministic evaluation over 30 episodes (start k % 3, '
             'target (k // 3) % 5, no tracking noise). Settings: the script\'s docstring.', '',
             '| variant | seed | env steps | success | collisions | mean episode length | '
             'training wall time | steps/s |', '|---|---|---|---|---|---|---|---|']
    for r in results:
        steps = f"{r['steps']:,}" if r['variant'] != 'bc' else f"0 ({r['bc_epochs']} epochs)"
        sps = f"{r['steps_per_s']:.0f}" if r.get('steps_per_s') else '-'
        lines.append(f"| {r['variant']} | {r['seed']} | {steps} | {r['success']}/{r['episodes']}"
                     f" | {r['collisions']}/{r['episodes']} | {r['mean_length']:.0f} | "
                     f"{r['train_wall_s']:.0f} s | {sps} |")
    curves = sorted(root.glob('*/curve.csv'))
    if curves and plot_curves(curves, out.parent / 'curve.png'):
        lines += ['', 'Training episodes (stochastic policy) per round:', '',
                  '![learning curves](curve.png)']
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines[4:]))
    print(f'crosscheck: report written to {out}')


def plot_curves(curves: list[Path], png: Path) -> bool:
    """Training success and episode length against steps, one line per run."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    import numpy as np

    fig, (ax_s, ax_l) = plt.subplots(1, 2, figsize=(10, 3.8))
    drawn = False
    for path in curves:
        rows = np.genfromtxt(path, delimiter=',', names=True, ndmin=1)
        if rows.size == 0:
            continue
        ax_s.plot(rows['steps'], 100 * rows['train_success'], '.-', label=path.parent.name)
        ax_l.plot(rows['steps'], rows['train_length'], '.-', label=path.parent.name)
        drawn = True
    if not drawn:
        plt.close(fig)
        return False
    ax_s.set(xlabel='env steps', ylabel='training success (%)', ylim=(-5, 105))
    ax_l.set(xlabel='env steps', ylabel='mean training episode length (steps)')
    ax_s.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return True


def crosscheck(args: argparse.Namespace) -> None:
    """Every seed of ``args.variant``, then the report (inside the venv)."""
    import warnings

    for path in reversed(PKG_PATHS):  # (run with the venv's python directly)
        if str(path) not in sys.path:
            sys.path.insert(0, str(path))
    import torch

    from cgail_learning.errors import LearningError

    torch.set_num_threads(args.threads)
    # imitation 1.0.1's BC logs a loss tensor with float(): harmless, and it would print per run
    warnings.filterwarnings('ignore', message='Converting a tensor with requires_grad=True')
    import imitation  # type: ignore[import-not-found]
    import stable_baselines3  # type: ignore[import-not-found]

    print(f'crosscheck: imitation {imitation.__version__}, stable-baselines3 '
          f'{stable_baselines3.__version__}, torch {torch.__version__}, {args.threads} torch '
          'thread(s)')
    if args.variant == 'bc':
        print(f'crosscheck: bc: imitation BC defaults (2 x 32 policy, batch 32, Adam 1e-3), '
              f'{args.bc_epochs} epochs')
    else:
        print(f'crosscheck: PPO ({args.ppo}) {ppo_kwargs(args.ppo) or "SB3 defaults"}, '
              f'{N_ENVS} envs')
        print(f'crosscheck: GAIL ({args.variant} reward) {gail_kwargs(args.disc_actions)}')
    t_start = time.monotonic()
    try:
        demos = load_transitions(args.demos)
    except LearningError as exc:  # missing bag, or a replay beyond the 1 mm tolerance
        raise CrosscheckError(str(exc)) from None
    print(f'crosscheck: demonstrations loaded in {time.monotonic() - t_start:.0f} s')
    for seed in args.seeds:
        run_dir = args.root / (f'{args.variant}{"_sb3ppo" * (args.ppo == "sb3")}'
                               f'{"_disc_actions" * bool(args.disc_actions)}_seed{seed}')
        run = run_bc if args.variant == 'bc' else run_gail
        result = run(args, seed, run_dir, demos)
        save_json(run_dir / 'result.json', result)
        print(f"crosscheck: {args.variant} seed {seed}: success {result['success']}/"
              f"{result['episodes']}, mean episode length {result['mean_length']:.0f} steps, "
              f"{result['steps']:,} env steps, training {result['train_wall_s']:.0f} s",
              flush=True)
    write_report(args.root, args.out or args.root / 'report.md')
    print(f'crosscheck: done in {time.monotonic() - t_start:.0f} s')


def main(argv: list[str] | None = None) -> int:
    raw = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--variant', choices=VARIANTS, default='standard',
                   help='GAIL reward (standard, shifted) or BC alone (bc)')
    p.add_argument('--steps', type=int, default=2_000_000,
                   help='env steps per GAIL run (rounded up to whole rounds of 10,240)')
    p.add_argument('--seeds', type=int, nargs='+', default=[0, 1])
    p.add_argument('--bc-epochs', type=int, default=5)
    p.add_argument('--ppo', choices=('ours', 'sb3'), default='ours',
                   help="PPO settings: ML-Agents' as our presets (default) or SB3's own defaults "
                        "(the gail preset's since 2026-12-02)")
    p.add_argument('--disc-actions', action='store_true',
                   help='the discriminator also sees the action (default: observation only)')
    p.add_argument('--resume', action='store_true',
                   help='continue each run from its checkpoint up to --steps')
    p.add_argument('--checkpoint-every', type=int, default=100_000, help='env steps')
    p.add_argument('--threads', type=int, default=1, help='torch threads')
    p.add_argument('--demos', type=Path, default=DEMOS)
    p.add_argument('--root', type=Path, default=WS / 'runs' / 'crosscheck_imitation',
                   help='where the venv and the runs live')
    p.add_argument('--venv', type=Path, default=None, help='default: ROOT/.venv')
    p.add_argument('--out', type=Path, default=None, help='default: ROOT/report.md')
    args = p.parse_args(raw)
    for name in ('steps', 'bc_epochs', 'checkpoint_every', 'threads'):
        if getattr(args, name) < 1:
            p.error(f'--{name.replace("_", "-")} must be >= 1, found {getattr(args, name)}')
    venv = (args.venv or args.root / '.venv').absolute()
    try:
        if not in_venv(venv):
            ensure_venv(venv)
            reexec_in_venv(venv, raw)
        crosscheck(args)
    except CrosscheckError as exc:
        print(f'crosscheck_imitation: error: {exc}', file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())
