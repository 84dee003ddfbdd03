"""The C-GAIL trainer: PPO + per-signal value heads + GAIL + BC + curiosity + curriculum.

Read top to bottom: :meth:`Trainer.collect` fills the rollout buffer from the batched env,
:meth:`Trainer.compute_rewards` evaluates every reward signal and the GAE, :meth:`Trainer.update`
runs the PPO epochs (with the discriminator and ICM steps on the same minibatches, as
ML-Agents does) and then the BC pass. See :mod:`cgail_learning.config` for how the
paper's loss weights map onto these mechanics.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
import math
from pathlib import Path
import random
from typing import Any

import numpy as np
import torch

from cgail_learning.bc import bc_passes, BehavioralCloning
from cgail_learning.buffer import RolloutBuffer
from cgail_learning.checkpoint import load_checkpoint
from cgail_learning.config import config_to_dict, TrainConfig
from cgail_learning.curiosity import Curiosity
from cgail_learning.curriculum import Curriculum
from cgail_learning.envs import is_success, VecEnv
from cgail_learning.errors import DemoError, PolicyLoadError
from cgail_learning.gail import Gail
from cgail_learning.networks import Actor, Critic, RunningNormalizer
from cgail_learning.ppo import linear_schedule, ppo_loss

#: Settings a resumed run may change (``train --resume --max-steps/--checkpoint-every``): the
#: budget (the linear schedules then decay towards the new end) and how often checkpoints are
#: written (nothing in training reads it).
RESUME_MAY_CHANGE = frozenset({'max_steps', 'checkpoint_every'})


def seed_everything(seed: int) -> np.random.Generator:
    """Seed python, numpy and torch in one place; return the trainer's numpy generator."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


@dataclass
class EpisodeStats:
    """Rolling statistics of finished training episodes."""

    rewards: deque[float]
    lengths: deque[int]
    successes: deque[float]


class Trainer:
    """One training run on a batched environment.

    Args:
        cfg: validated training configuration.
        env: batched environment (see :class:`cgail_learning.envs.VecEnv`).
        demo_obs: (M, obs_dim) demonstration observations (required when GAIL or BC is on).
        demo_act: (M, act_dim) demonstration actions in [-1, 1].
        seed: seeds torch, numpy and the envs; the same seed reproduces the run.
        metadata: free-form data stored in checkpoints (observation layout, anatomy...).
        demo_episodes: how many episodes the demonstrations hold (required with GAIL: each
            ends in the discriminator's absorbing state, :mod:`cgail_learning.gail`).
    """

    def __init__(self, cfg: TrainConfig, env: VecEnv, *, demo_obs: np.ndarray | None = None,
                 demo_act: np.ndarray | None = None, seed: int = 0,
                 metadata: dict[str, Any] | None = None,
                 demo_episodes: int | None = None) -> None:
        self.cfg, self.env, self.seed = cfg, env, seed
        self.rng = seed_everything(seed)
        self.obs_dim = int(env.single_observation_space.shape[0])
        self.act_dim = int(env.single_action_space.shape[0])
        self.metadata = dict(metadata or {})
        self.signals = cfg.signals()
        self.normalizer = RunningNormalizer(self.obs_dim) if cfg.normalize else None
        self.actor = Actor(self.obs_dim, self.act_dim, cfg.network, self.normalizer)
        self.critic = Critic(self.obs_dim, list(self.signals), cfg.network, self.normalizer)
        params = [p for p in self.actor.parameters()] + [
            p for n, p in self.critic.named_parameters() if not n.startswith('normalizer')]
        self.opt = torch.optim.Adam(params, lr=cfg.ppo.learning_rate)
        self.demo_obs = self.demo_act = None
        if cfg.needs_demos:
            if demo_obs is None or demo_act is None or len(demo_obs) == 0:
                raise DemoError(f'preset {cfg.name!r} uses GAIL/BC: expected demonstrations, '
                                'found none')
            if demo_obs.shape[1:] != (self.obs_dim,) or demo_act.shape[1:] != (self.act_dim,):
                raise DemoError(f'demonstrations do not match the env: expected obs '
                                f'(M, {self.obs_dim}) and act (M, {self.act_dim}), found '
                                f'{demo_obs.shape} and {demo_act.shape}')
            self.demo_obs = torch.as_tensor(demo_obs, dtype=torch.float32)
            self.demo_act = torch.as_tensor(np.clip(demo_act, -1, 1), dtype=torch.float32)
        self.gail = Gail(self.obs_dim, self.act_dim, cfg.gail) if 'gail' in self.signals \
            else None
        self.demo_episodes = 0
        if self.gail is not None:
            assert self.demo_obs is not None
            if demo_episodes is None or not 1 <= demo_episodes <= len(self.demo_obs):
                raise DemoError(f'preset {cfg.name!r} uses GAIL: expected the number of '
                                f'demonstration episodes, in [1, {len(self.demo_obs)}] (each '
                                f'ends in the absorbing state), found {demo_episodes!r}')
            self.demo_episodes = int(demo_episodes)
        self.curiosity = Curiosity(self.obs_dim, self.act_dim, cfg.curiosity) \
            if 'curiosity' in self.signals else None
        self.bc = None
        if cfg.bc.strength > 0:
            assert demo_obs is not None and demo_act is not None
            self.bc = BehavioralCloning(self.actor, demo_obs, np.clip(demo_act, -1, 1), cfg.bc,
                                        cfg.ppo.learning_rate)
        self.curriculum = Curriculum(cfg.curriculum)
        self.step = 0
        self.n_updates = 0
        self.stats = EpisodeStats(deque(maxlen=100), deque(maxlen=100), deque(maxlen=100))
        #: Training episodes a simulation fault ended (the env's ``info["simulation_fault"]``:
        #: truncated, so bootstrapped like the step limit), since the start of this run.
        self.simulation_faults = 0
        self.steps_per_rollout = math.ceil(cfg.ppo.buffer_size / env.num_envs)
        self.buffer = RolloutBuffer(self.steps_per_rollout, env.num_envs, self.obs_dim,
                                    self.act_dim, list(self.signals))
        self._ep_reward = np.zeros(env.num_envs)
        self._ep_len = np.zeros(env.num_envs, dtype=np.int64)
        if self.curriculum.theta_max is not None:
            env.set_theta_max(self.curriculum.theta_max)
        self._obs = env.reset(seed=seed)
        if self.normalizer is not None:
            self.normalizer.update(self._obs)

    # ---------------------------------------------------------------- rollout
    @torch.no_grad()
    def collect(self) -> None:
        """Fill the buffer with ``steps_per_rollout`` batched steps of the stochastic policy."""
        self.buffer.pos = 0
        while not self.buffer.full:
            obs_t = torch.as_tensor(self._obs)
            dist = self.actor.distribution(obs_t)
            act = dist.sample()
            logp = dist.log_prob(act).sum(-1)
            values = {s: v.numpy() for s, v in self.critic(obs_t).items()}
            act_np = act.numpy()
            next_obs, rew, term, trunc, infos = self.env.step(np.clip(act_np, -1.0, 1.0))
            ended = term | trunc
            final_obs = next_obs.copy()
            for i in np.flatnonzero(ended):
                final_obs[i] = infos[i].get('final_obs', next_obs[i])
            self.buffer.add(self._obs, act_np, logp.numpy(), rew, final_obs, term, ended, values)
            self._ep_reward += rew
            self._ep_len += 1
            for i in np.flatnonzero(ended):
                self.simulation_faults += bool(infos[i].get('simulation_fault', False))
                self._finish_episode(int(i), is_success(infos[i]))
            self._obs = next_obs
            self.step += self.env.num_envs

    def _finish_episode(self, i: int, success: bool) -> None:
        self.stats.rewards.append(float(self._ep_reward[i]))
        self.stats.lengths.append(int(self._ep_len[i]))
        self.stats.successes.append(float(success))
        if self.curriculum.record(float(self._ep_reward[i]), success):
            theta = self.curriculum.theta_max
            assert theta is not None
            self.env.set_theta_max(theta)
        self._ep_reward[i] = 0.0
        self._ep_len[i] = 0

    @torch.no_grad()
    def compute_rewards(self) -> dict[str, float]:
        """Per-signal rewards (scaled by strength), bootstrap values and GAE over the buffer."""
        b = self.buffer
        n = b.T * b.N
        obs = torch.as_tensor(b.obs.reshape(n, -1))
        nobs = torch.as_tensor(b.next_obs.reshape(n, -1))
        act = torch.as_tensor(np.clip(b.act.reshape(n, -1), -1, 1))
        nobs_n, obs_n = self.actor.norm(nobs), self.actor.norm(obs)
        out: dict[str, float] = {}
        for s, sig in self.signals.items():
            if s == 'extrinsic':
                r = b.env_rewards.reshape(n)
            elif s == 'gail':  # relative to the absorbing state's reward (gail.py)
                assert self.gail is not None
                if self.cfg.gail.reward_form == 'standard':
                    r = self.gail.reward(obs_n, act)
                else:
                    r_abs = self.gail.absorbing_reward()
                    r = self.gail.step_reward(obs_n, act, r_abs)
                    out['rewards/gail_absorbing'] = r_abs
            else:
                assert self.curiosity is not None
                r = self.curiosity.reward(obs_n, act, nobs_n)
            b.rewards[s] = (sig.strength * r).reshape(b.T, b.N).astype(np.float32)
            out[f'rewards/{s}_mean'] = float(b.rewards[s].mean())
        next_values = self.critic(nobs)
        for s in self.signals:
            b.next_values[s] = next_values[s].numpy().reshape(b.T, b.N)
        b.finish({s: sig.gamma for s, sig in self.signals.items()}, self.cfg.ppo.lambd)
        return out

    # ---------------------------------------------------------------- update
    def update(self) -> dict[str, float]:
        """PPO epochs (+ discriminator and ICM steps per minibatch), then the BC pass."""
        cfg = self.cfg.ppo
        lr = linear_schedule(cfg.learning_rate, 1e-10, self.step, self.cfg.max_steps,
                             cfg.schedule)
        eps = linear_schedule(cfg.epsilon, 0.1, self.step, self.cfg.max_steps, cfg.schedule)
        beta = linear_schedule(cfg.beta, 1e-5, self.step, self.cfg.max_steps, cfg.schedule)
        for g in self.opt.param_groups:
            g['lr'] = lr
        acc: dict[str, list[float]] = {}

        def add(d: dict[str, float]) -> None:
            for k, v in d.items():
                acc.setdefault(k, []).append(v)

        for _ in range(cfg.num_epoch):
            for mb in self.buffer.minibatches(cfg.batch_size, self.rng):
                obs = torch.as_tensor(mb.obs)
                act = torch.as_tensor(mb.act)
                loss, st = ppo_loss(
                    self.actor, self.critic, obs, act, torch.as_tensor(mb.logp),
                    torch.as_tensor(mb.advantages),
                    {s: torch.as_tensor(v) for s, v in mb.returns.items()},
                    {s: torch.as_tensor(v) for s, v in mb.old_values.items()},
                    eps, beta, cfg.value_coef, cfg.clip_value_loss,
                    cfg.advantage_normalization == 'minibatch')
                self.opt.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
                torch.nn.utils.clip_grad_norm_(self.critic.parameters(), cfg.max_grad_norm)
                self.opt.step()
                add({'losses/policy_loss': st.policy_loss, 'losses/value_loss': st.value_loss,
                     'policy/entropy': st.entropy, 'losses/approx_kl': st.approx_kl,
                     'losses/clip_fraction': st.clip_fraction})
                with torch.no_grad():
                    obs_n = self.actor.norm(obs)
                    act_c = torch.clamp(act, -1, 1)
                if self.gail is not None and not self.cfg.gail.updates_per_buffer:
                    add(self._gail_step(obs_n, act_c, mb.terminated))
                if self.curiosity is not None:
                    with torch.no_grad():
                        nobs_n = self.actor.norm(torch.as_tensor(mb.next_obs))
                    add(self.curiosity.update(obs_n, act_c, nobs_n))
        if self.gail is not None and self.cfg.gail.updates_per_buffer:
            b = self.buffer
            n = b.T * b.N
            size = min(self.cfg.gail.batch_size, n)
            for _ in range(self.cfg.gail.updates_per_buffer):
                j = self.rng.choice(n, size, replace=False)
                with torch.no_grad():
                    obs_n = self.actor.norm(torch.as_tensor(b.obs.reshape(n, -1)[j]))
                act_c = torch.as_tensor(np.clip(b.act.reshape(n, -1)[j], -1, 1))
                add(self._gail_step(obs_n, act_c, b.terminated.reshape(n)[j]))
        if self.bc is not None:
            add(self.bc.update(self.step, lr, self.cfg.ppo.buffer_size, self.rng))
        if self.normalizer is not None:
            self.normalizer.update(self.buffer.obs.reshape(-1, self.obs_dim))
        self.n_updates += 1
        out = {k: float(np.mean(v)) for k, v in acc.items()}
        out.update({'policy/learning_rate': lr, 'policy/epsilon': eps, 'policy/beta': beta,
                    'policy/std': float(self.actor.log_std.detach().exp().mean())})
        return out

    def _gail_step(self, obs_n: torch.Tensor, act_c: torch.Tensor,
                   terminated: np.ndarray) -> dict[str, float]:
        """One discriminator step on these (normalised, clipped) policy transitions and as many
        demonstration samples. With the absorbing reward, the expert side holds one absorbing
        sample per demonstration episode among its draws, the policy side one per terminated
        transition."""
        assert self.gail is not None
        assert self.demo_obs is not None and self.demo_act is not None
        n_demo = len(self.demo_obs)
        dac = self.cfg.gail.reward_form == 'absorbing'
        draw = self.rng.integers(0, n_demo + self.demo_episodes * dac, len(obs_n))
        idx = torch.as_tensor(draw[draw < n_demo])
        with torch.no_grad():
            ex_obs = self.actor.norm(self.demo_obs[idx])
        return self.gail.update(ex_obs, self.demo_act[idx], obs_n, act_c,
                                expert_absorbing=int((draw >= n_demo).sum()) * dac,
                                policy_absorbing=int(terminated.sum()) * dac)

    def train_iteration(self) -> dict[str, float]:
        """Collect one buffer, compute rewards/advantages, update; return the scalars."""
        self.collect()
        scalars = self.compute_rewards()
        scalars.update(self.update())
        if self.stats.rewards:
            scalars['environment/episode_reward'] = float(np.mean(self.stats.rewards))
            scalars['environment/episode_length'] = float(np.mean(self.stats.lengths))
            scalars['environment/success_rate'] = float(np.mean(self.stats.successes))
        scalars['environment/simulation_faults'] = float(self.simulation_faults)
        if self.curriculum.enabled:
            scalars['curriculum/lesson'] = float(self.curriculum.lesson)
            scalars['curriculum/theta_max_deg'] = math.degrees(self.curriculum.theta_max or 0.0)
        return scalars

    def pretrain_bc(self, epochs: int, learning_rate: float = 1e-3, batch_size: int = 512,
                    refit_normalizer: bool = True,
                    extra: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, float]:
        """Behavioural-cloning warm start: ``epochs`` supervised passes over the demonstrations
        before any environment step (the actor only; the critic and the discriminator learn
        from the rollouts that follow).

        The in-loop BC of :meth:`update` runs at ``strength * policy lr`` (4e-5 with the
        ``cgail`` preset) on one buffer's worth of demos per update: it keeps a policy near the
        expert but cannot teach a new anatomy quickly. Measured on a patient anatomy
        (``plan_patient``): fine-tuning the committed policy with C-GAIL from 60 demonstrations
        reached 64% on unseen targets in 13 min; supervised BC on 255 demonstrations reached
        96% from a random network, and this warm start from the committed policy 100% (through
        the simulated tracker noise), in about 20 s and before any RL step.

        Args:
            epochs: passes over the demonstrations (>= 1).
            learning_rate: Adam learning rate of the warm start.
            batch_size: minibatch size.
            refit_normalizer: set the observation normaliser to the demonstrations' mean and
                variance first (a base policy's statistics come from another anatomy).
            extra: more (obs, act) pairs cloned with the demonstrations, e.g. the expert's
                labels of the learner's own states (:mod:`cgail_learning.dagger`). They
                are used by this warm start only; GAIL's expert buffer and the in-loop BC keep
                the demonstrations alone (a discriminator must not learn the learner's states
                as expert ones).

        Returns:
            ``{'losses/bc_pretrain_loss': last epoch's mean loss, 'bc_pretrain/epochs': n}``.
        """
        if self.demo_obs is None or self.demo_act is None:
            raise DemoError('pretrain_bc: expected demonstrations, found none (the preset '
                            'uses neither GAIL nor BC)')
        if epochs < 1 or batch_size < 1 or not learning_rate > 0:
            raise ValueError(f'pretrain_bc: expected epochs >= 1, batch_size >= 1 and '
                             f'learning_rate > 0, found {epochs}, {batch_size}, '
                             f'{learning_rate}')
        obs, act = self.demo_obs, self.demo_act
        if extra is not None:
            e_obs, e_act = (np.asarray(x, np.float32) for x in extra)
            if e_obs.ndim != 2 or e_obs.shape[1:] != obs.shape[1:] or \
                    e_act.shape != (len(e_obs), act.shape[1]) or not np.isfinite(e_obs).all():
                raise DemoError(f'pretrain_bc: expected extra finite (obs, act) pairs shaped '
                                f'(M, {obs.shape[1]}) and (M, {act.shape[1]}), found '
                                f'{e_obs.shape} and {e_act.shape}')
            obs = torch.cat([obs, torch.as_tensor(e_obs)])
            act = torch.cat([act, torch.as_tensor(np.clip(e_act, -1, 1))])
        if self.normalizer is not None and refit_normalizer:
            self.normalizer.fit(obs)
        opt = torch.optim.Adam(self.actor.parameters(), lr=learning_rate)
        losses = bc_passes(self.actor, obs, act, opt, epochs, batch_size, self.rng)
        return {'losses/bc_pretrain_loss': losses[-1],
                'bc_pretrain/epochs': float(epochs)}

    # ---------------------------------------------------------------- evaluation
    @torch.no_grad()
    def act_deterministic(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic action(s) for raw observation(s)."""
        o = torch.as_tensor(np.asarray(obs, np.float32))
        return self.actor.deterministic(o).numpy()

    # ---------------------------------------------------------------- checkpoints
    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        opts: dict[str, torch.optim.Optimizer] = {'ppo': self.opt}
        for name, part in (('gail', self.gail), ('curiosity', self.curiosity), ('bc', self.bc)):
            if part is not None:
                opts[name] = part.opt
        return opts

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume (:meth:`resume`), export or fine-tune."""
        return {
            'config': config_to_dict(self.cfg), 'step': self.step, 'seed': self.seed,
            'obs_dim': self.obs_dim, 'act_dim': self.act_dim, 'metadata': self.metadata,
            'actor': self.actor.state_dict(), 'critic': self.critic.state_dict(),
            'normalizer': None if self.normalizer is None else self.normalizer.state_dict(),
            'gail': None if self.gail is None else self.gail.disc.state_dict(),
            'curiosity': None if self.curiosity is None else self.curiosity.icm.state_dict(),
            'curriculum_lesson': self.curriculum.lesson,
            'resume': {
                'n_updates': self.n_updates,
                'optimizers': {k: o.state_dict() for k, o in self._optimizers().items()},
                'numpy_rng': self.rng.bit_generator.state,
                'torch_rng': torch.get_rng_state(),
                'curriculum_window': list(self.curriculum._window),
                'episodes': [list(self.stats.rewards), list(self.stats.lengths),
                             list(self.stats.successes)],
                'curiosity_updated': bool(self.curiosity is not None and self.curiosity.updated),
            },
        }

    def save(self, path: Path, run: dict[str, Any] | None = None) -> None:
        """Write a checkpoint (torch.save of :meth:`state_dict`; ``run``: the training loop's
        own state, kept for :func:`cgail_learning.train.run_training` to resume)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        state = self.state_dict()
        if run is not None:
            state['run'] = dict(run)
        tmp = path.with_name(path.name + '.tmp')
        torch.save(state, tmp)
        tmp.replace(path)  # (a run killed while saving leaves the previous file whole)

    def resume(self, ckpt: dict[str, Any], path: Path) -> None:
        """Continue a run from its checkpoint ``ckpt`` (read from ``path``): networks,
        normaliser, optimisers, schedules (from the step count), curriculum, episode
        statistics and random streams.

        The environments start new episodes (seeded ``seed + step``): the episodes in progress
        when the checkpoint was written are not stored, so a resumed run continues the run
        rather than replaying it bit for bit.

        ``max_steps`` may differ from the checkpoint's (a run extended to a larger budget: the
        linear schedules then decay towards the new end from the current step).

        Raises:
            PolicyLoadError: a checkpoint without the resume state (written before it existed,
                or by ``export``), or of another preset or observation size.
        """
        state = ckpt.get('resume')
        if state is None:
            raise PolicyLoadError(f'{path}: expected a checkpoint with its resume state '
                                  '(train writes one every checkpoint_every steps), found a '
                                  'checkpoint without it; use --init-from to fine-tune from it')
        # (the budget and the checkpoint interval may change on resume: neither alters training)
        mine = {k: v for k, v in config_to_dict(self.cfg).items() if k not in RESUME_MAY_CHANGE}
        theirs = {k: v for k, v in ckpt['config'].items() if k not in RESUME_MAY_CHANGE}
        if mine != theirs or ckpt['obs_dim'] != self.obs_dim:
            differ = sorted(k for k in {*mine, *theirs} if mine.get(k) != theirs.get(k))
            raise PolicyLoadError(f'{path}: expected a checkpoint of this configuration '
                                  f'(preset {self.cfg.name!r}, obs dim {self.obs_dim}), found '
                                  f'preset {ckpt["config"].get("name")!r}, obs dim '
                                  f'{ckpt["obs_dim"]}'
                                  + (f', other {", ".join(differ)}' if differ else ''))
        try:
            self.actor.load_state_dict(ckpt['actor'])
            self.critic.load_state_dict(ckpt['critic'])
            if self.gail is not None:
                self.gail.disc.load_state_dict(ckpt['gail'])
            if self.curiosity is not None:
                self.curiosity.icm.load_state_dict(ckpt['curiosity'])
                self.curiosity.updated = bool(state['curiosity_updated'])
            opts = self._optimizers()
            if set(opts) != set(state['optimizers']):
                raise KeyError(f'optimisers {sorted(state["optimizers"])}')
            for k, o in opts.items():
                o.load_state_dict(state['optimizers'][k])
        except (RuntimeError, KeyError, ValueError) as exc:
            raise PolicyLoadError(f'{path}: the checkpoint does not fit this run: '
                                  f'{str(exc).splitlines()[0]}') from None
        self.step = int(ckpt['step'])
        self.n_updates = int(state['n_updates'])
        self.rng.bit_generator.state = state['numpy_rng']
        torch.set_rng_state(state['torch_rng'])
        self.curriculum.lesson = int(ckpt['curriculum_lesson'])
        self.curriculum._window.extend(state['curriculum_window'])
        rewards, lengths, successes = state['episodes']
        self.stats.rewards.clear()
        self.stats.rewards.extend(rewards)
        self.stats.lengths.clear()
        self.stats.lengths.extend(lengths)
        self.stats.successes.clear()
        self.stats.successes.extend(successes)
        if self.curriculum.theta_max is not None:
            self.env.set_theta_max(self.curriculum.theta_max)
        self._ep_reward[:] = 0.0
        self._ep_len[:] = 0
        self._obs = self.env.reset(seed=self.seed + self.step)

    def load_weights(self, path: Path) -> None:
        """Initialise from a checkpoint (``--init-from``): networks + normaliser, new step count.

        Value heads and discriminator/ICM are loaded where the signal exists in both runs. An
        exported ``.onnx`` policy gives the actor and its normaliser only
        (:func:`cgail_learning.export.actor_state_from_onnx`): the value heads, the
        discriminator and the ICM start fresh, and ``log_std`` keeps the preset's initial value.
        """
        if Path(path).suffix == '.onnx':
            from cgail_learning.export import actor_state_from_onnx

            state = actor_state_from_onnx(Path(path))
            state['log_std'] = self.actor.log_std.detach().clone()
            if (self.normalizer is None) != ('normalizer.mean' not in state):
                raise PolicyLoadError(f'{path}: expected a policy '
                                      f'{"without" if self.normalizer is None else "with"} an '
                                      'observation normaliser (the preset\'s normalize), found '
                                      'the other')
            try:
                self.actor.load_state_dict(state)
            except RuntimeError as exc:
                raise PolicyLoadError(f'{path}: network shapes differ from this preset: '
                                      f'{str(exc).splitlines()[0]} (expected '
                                      f'{self.cfg.network.num_layers} x '
                                      f'{self.cfg.network.hidden_units} units)') from None
            return
        ckpt = load_checkpoint(path)
        if ckpt['obs_dim'] != self.obs_dim or ckpt['act_dim'] != self.act_dim:
            raise PolicyLoadError(f'{path}: expected obs/act dims ({self.obs_dim}, '
                                  f'{self.act_dim}), found ({ckpt["obs_dim"]}, '
                                  f'{ckpt["act_dim"]})')
        try:
            self.actor.load_state_dict(ckpt['actor'])
            self.critic.load_state_dict(ckpt['critic'], strict=False)
            if self.gail is not None and ckpt.get('gail') is not None:
                self.gail.disc.load_state_dict(ckpt['gail'])
            if self.curiosity is not None and ckpt.get('curiosity') is not None:
                self.curiosity.icm.load_state_dict(ckpt['curiosity'])
                self.curiosity.updated = True
        except RuntimeError as exc:
            raise PolicyLoadError(f'{path}: network shapes differ from this preset: {exc}') \
                from None


def evaluate_policy(policy: Callable[[np.ndarray], np.ndarray], env: Any, episodes: int,
                    seed: int) -> dict[str, float]:
    """Run ``episodes`` episodes of a deterministic policy on a single gym env."""
    succ, rews, lens = [], [], []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        total, n = 0.0, 0
        while True:
            obs, r, te, tr, info = env.step(policy(obs))
            total += float(r)
            n += 1
            if te or tr:
                break
        succ.append(float(is_success(info)))
        rews.append(total)
        lens.append(n)
    return {'eval/success_rate': float(np.mean(succ)), 'eval/episode_reward': float(np.mean(rews)),
            'eval/episode_length': float(np.mean(lens))}
