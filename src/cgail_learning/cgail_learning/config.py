"""Training configuration: frozen dataclasses, validated at construction, loaded from YAML presets.

How the paper's loss maps onto the implementation
-------------------------------------------------
The paper (eq. 7) writes the C-GAIL objective as

    L = kappa (1 - mu) L_PPO + lambda L_GAIL + kappa mu L_BC + nu L_curiosity

with kappa = 0.2, lambda = 0.8, mu = 0.7, nu = 0.02, and states that all parameters are those of
the Unity ML-Agents toolkit. ML-Agents has no single weighted loss; each coefficient is a
*strength* with the following meaning, which this trainer reproduces exactly:

* ``kappa (1 - mu)`` = 0.06 is the strength of the **extrinsic** reward signal: the environment
  reward is multiplied by it before its own value head and GAE (``RewardSignalConfig.strength``
  of ``extrinsic``). L_PPO is the clipped-surrogate PPO loss driven by the advantages.
* ``lambda`` = 0.8 is the strength of the **GAIL** reward signal: the discriminator reward
  ``-log(1 - D(s))`` (ML-Agents' form, with a learned absorbing state for episode ends:
  :mod:`cgail_learning.gail`) is multiplied by it (own value head, own gamma 0.99). The
  discriminator itself is trained with its own loss (binary cross-entropy + gradient penalty)
  and optimiser; lambda scales what it contributes to the policy, i.e. L_GAIL's effect.
* ``kappa mu`` = 0.14 is the strength of **behavioural cloning**: after each PPO update one
  supervised pass over the demonstrations runs with learning rate ``strength * learning_rate``
  (ML-Agents ``behavioral_cloning.strength``).
* ``nu`` = 0.02 is the strength of the **curiosity** (ICM) reward signal: the forward-model
  error, capped so that ``strength * r <= 1``, multiplied by nu (own value head).

Each reward signal has its own value head; the advantage is the mean of the per-signal GAE
advantages, normalised over the buffer (ML-Agents ``_process_trajectory``/``_update_policy``).
The per-update loss is ``L_clip + 0.5 * sum_signals L_value - beta * entropy``; beta, epsilon and
the learning rate decay linearly to their floors over ``max_steps``.

Presets live in ``config/presets/<name>.yaml``; :func:`load_config` reads one and every unknown
key or out-of-range value raises :class:`ConfigError` naming the key and the allowed range.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass
import math
from pathlib import Path
from typing import Any

import yaml

from cgail_learning.errors import ConfigError

PRESET_DIR = Path(__file__).resolve().parents[1] / 'config' / 'presets'
"""Directory of the YAML presets (cgail, gail, mu0, lambda0, nu0, smoke, and the ``paper_code_*``
presets of the authors' runs, which select the ``paper_code`` env option set)."""


def _check(cond: bool, name: str, expected: str, value: object) -> None:
    if not cond:
        raise ConfigError(f'{name} must be {expected}, found {value!r}')


@dataclass(frozen=True)
class NetworkConfig:
    """Policy / value network shape."""

    hidden_units: int = 128
    """Units per hidden layer (ML-Agents default 128; the GAIL baseline uses 64)."""
    num_layers: int = 2
    """Number of hidden layers (1..8)."""
    activation: str = 'swish'
    """Hidden activation: ``swish`` (ML-Agents' default, SiLU), ``tanh`` or ``relu``."""
    init_log_std: float = 0.0
    """Initial log standard deviation of the Gaussian policy (-5..2)."""
    orthogonal_init: bool = False
    """Orthogonal initialisation of the hidden layers (gain sqrt 2) and the value heads (gain
    1), as stable-baselines3's PPO does (``ortho_init``); False keeps PyTorch's default (as
    ML-Agents). The policy's mean layer is orthogonal with gain 0.01 either way."""

    def __post_init__(self) -> None:
        _check(1 <= self.hidden_units <= 4096, 'network.hidden_units', 'in [1, 4096]',
               self.hidden_units)
        _check(1 <= self.num_layers <= 8, 'network.num_layers', 'in [1, 8]', self.num_layers)
        _check(self.activation in ('swish', 'tanh', 'relu'), 'network.activation',
               "one of 'swish', 'tanh', 'relu'", self.activation)
        _check(-5.0 <= self.init_log_std <= 2.0, 'network.init_log_std', 'in [-5, 2]',
               self.init_log_std)


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters (ML-Agents names in brackets)."""

    learning_rate: float = 3.0e-4
    """Initial Adam learning rate, linearly decayed to 1e-10 over max_steps."""
    batch_size: int = 1024
    """Minibatch size of each gradient step [batch_size]."""
    buffer_size: int = 10240
    """Transitions collected per update [buffer_size]; a multiple of batch_size."""
    num_epoch: int = 3
    """Passes over the buffer per update [num_epoch]."""
    beta: float = 5.0e-4
    """Initial entropy coefficient, linearly decayed to 1e-5 [beta]."""
    epsilon: float = 0.2
    """Initial clip range, linearly decayed to 0.1 [epsilon]."""
    lambd: float = 0.95
    """GAE lambda, shared by all reward signals [lambd]."""
    value_coef: float = 0.5
    """Weight of the summed value losses."""
    max_grad_norm: float = 0.5
    """Gradient clipping norm."""
    schedule: str = 'linear'
    """``linear`` (decay over max_steps) or ``constant``."""
    advantage_normalization: str = 'buffer'
    """``buffer``: advantages normalised once over the whole buffer (ML-Agents); ``minibatch``:
    normalised again within every minibatch (stable-baselines3's ``normalize_advantage``)."""
    clip_value_loss: bool = True
    """Clip the value loss around the old values with ``epsilon`` (ML-Agents); False: the plain
    squared error (stable-baselines3's default ``clip_range_vf=None``)."""

    def __post_init__(self) -> None:
        _check(self.advantage_normalization in ('buffer', 'minibatch'),
               'ppo.advantage_normalization', "'buffer' or 'minibatch'",
               self.advantage_normalization)
        _check(0 < self.learning_rate <= 1, 'ppo.learning_rate', 'in (0, 1]', self.learning_rate)
        _check(1 <= self.batch_size <= 1_000_000, 'ppo.batch_size', 'in [1, 1e6]',
               self.batch_size)
        _check(self.buffer_size >= self.batch_size and self.buffer_size % self.batch_size == 0,
               'ppo.buffer_size', f'a multiple of batch_size {self.batch_size}',
               self.buffer_size)
        _check(1 <= self.num_epoch <= 100, 'ppo.num_epoch', 'in [1, 100]', self.num_epoch)
        _check(0 <= self.beta <= 1, 'ppo.beta', 'in [0, 1]', self.beta)
        _check(0 < self.epsilon < 1, 'ppo.epsilon', 'in (0, 1)', self.epsilon)
        _check(0 <= self.lambd <= 1, 'ppo.lambd', 'in [0, 1]', self.lambd)
        _check(0 <= self.value_coef <= 10, 'ppo.value_coef', 'in [0, 10]', self.value_coef)
        _check(0 < self.max_grad_norm <= 100, 'ppo.max_grad_norm', 'in (0, 100]',
               self.max_grad_norm)
        _check(self.schedule in ('linear', 'constant'), 'ppo.schedule',
               "'linear' or 'constant'", self.schedule)


@dataclass(frozen=True)
class RewardSignalConfig:
    """One reward signal (extrinsic, gail or curiosity); strength 0 disables it."""

    strength: float = 0.0
    """Multiplier of the signal's reward (the paper's kappa(1-mu), lambda or nu), in [0, 10]."""
    gamma: float = 0.99
    """Discount of this signal's value head, in [0, 1)."""

    def __post_init__(self) -> None:
        _check(0 <= self.strength <= 10, 'strength', 'in [0, 10]', self.strength)
        _check(0 <= self.gamma < 1, 'gamma', 'in [0, 1)', self.gamma)


@dataclass(frozen=True)
class GailConfig(RewardSignalConfig):
    """GAIL discriminator settings (ML-Agents ``reward_signals.gail``)."""

    hidden_units: int = 128
    """Discriminator hidden units per layer."""
    learning_rate: float = 3.0e-4
    """Discriminator Adam learning rate."""
    use_actions: bool = False
    """Discriminate (s, a) instead of s alone (ML-Agents default False)."""
    gradient_penalty: float = 1.0
    """Weight of the penalty (||grad logit D(x_hat)|| - 1)^2 on expert/policy interpolates."""
    reward_form: str = 'absorbing'
    """``absorbing``: ``-log(1 - D(s)) - r_abs`` with DAC's learned absorbing state
    (:mod:`cgail_learning.gail`); ``standard``: ML-Agents' ``-log(1 - D(s))`` alone,
    never negative (the authors' runs, ML-Agents 0.29; the ``imitation`` cross-check's GAIL).
    Measured on the default aorta, preset ``gail``, 2M steps: ``absorbing`` 0/30 for seeds 0 and
    1 (evaluation episodes of 80-1,300 steps, r_abs 0.3-0.6 above the policy states' ~0.16, so
    ending still paid)."""

    updates_per_buffer: int = 0
    """Discriminator gradient steps per collected buffer. ``0``: one step per PPO minibatch, on
    that minibatch and as many demonstration samples, during the PPO epochs (ML-Agents: its
    reward signals update with the policy, ``num_epoch x buffer_size / batch_size`` steps).
    ``N > 0``: N steps after the PPO epochs, each on ``batch_size`` policy transitions drawn
    from the buffer and as many demonstration samples (the ``imitation`` library's
    ``n_disc_updates_per_round`` and ``demo_batch_size``): the discriminator's pace no longer
    follows the PPO minibatch size."""
    batch_size: int = 1024
    """Policy (and demonstration) samples per discriminator step when ``updates_per_buffer``
    is set; at most the buffer size."""
    own_normalizer: bool = False
    """False: the discriminator reads observations through the policy's normaliser (ML-Agents).
    True: it normalises its own input (observation and action) with running statistics of
    every expert and policy batch it trains on, unclipped (the ``imitation`` library's
    ``BasicRewardNet(normalize_input_layer=RunningNorm)``)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _check(0 <= self.updates_per_buffer <= 10_000, 'gail.updates_per_buffer',
               'in [0, 10000] (0: one per PPO minibatch)', self.updates_per_buffer)
        _check(1 <= self.batch_size <= 1_000_000, 'gail.batch_size', 'in [1, 1e6]',
               self.batch_size)
        _check(self.reward_form in ('absorbing', 'standard'), 'gail.reward_form',
               "'absorbing' or 'standard'", self.reward_form)
        _check(1 <= self.hidden_units <= 4096, 'gail.hidden_units', 'in [1, 4096]',
               self.hidden_units)
        _check(0 < self.learning_rate <= 1, 'gail.learning_rate', 'in (0, 1]',
               self.learning_rate)
        _check(0 <= self.gradient_penalty <= 1000, 'gail.gradient_penalty', 'in [0, 1000]',
               self.gradient_penalty)


@dataclass(frozen=True)
class CuriosityConfig(RewardSignalConfig):
    """Intrinsic curiosity module settings (ML-Agents ``reward_signals.curiosity``)."""

    encoding_size: int = 64
    """Size of the learned state encoding."""
    learning_rate: float = 3.0e-4
    """ICM Adam learning rate."""
    forward_weight: float = 0.2
    """Weight of the forward loss in the ICM loss (inverse gets 1 - forward_weight)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _check(1 <= self.encoding_size <= 4096, 'curiosity.encoding_size', 'in [1, 4096]',
               self.encoding_size)
        _check(0 < self.learning_rate <= 1, 'curiosity.learning_rate', 'in (0, 1]',
               self.learning_rate)
        _check(0 <= self.forward_weight <= 1, 'curiosity.forward_weight', 'in [0, 1]',
               self.forward_weight)


#: The BC learning-rate and sample schedules (:attr:`BCConfig.schedule`).
BC_SCHEDULES = ('ours', 'ml-agents')


@dataclass(frozen=True)
class BCConfig:
    """Behavioural cloning (ML-Agents ``behavioral_cloning``)."""

    strength: float = 0.0
    """Learning-rate multiplier of the BC step (the paper's kappa*mu); 0 disables BC."""
    batch_size: int = 512
    """Demonstration minibatch size."""
    num_epoch: int = 3
    """Minibatch passes per PPO update, each over at most buffer_size demo samples
    (``schedule: ml-agents``: over every demo sample)."""
    steps: int = 0
    """BC strength decays linearly to 0 over these steps; 0 keeps it constant."""
    schedule: str = field(default='ours', metadata={'omit_default': True})
    """``ours``: the BC learning rate is the policy's (itself decaying over max_steps) times the
    strength (decaying over ``steps``), each of ``num_epoch`` passes over at most
    ``ppo.buffer_size`` shuffled demo samples. ``ml-agents``: as ML-Agents' ``BCModule``
    (0.29, which the authors ran): ``strength`` x the *initial* policy lr, decayed once,
    linearly to 1e-10 over ``steps`` (constant when 0), each pass over the whole demo buffer
    (their ``samples_per_update`` 0). Written to config dicts only when not ``ours``, so the
    configs (and checkpoints) of the presets that keep it are unchanged."""
    pretrain_epochs: int = 0
    """Supervised BC passes over the demonstrations before any environment step
    (:meth:`~cgail_learning.trainer.Trainer.pretrain_bc`, lr 1e-3, minibatch 512, the
    normaliser fitted to the demonstrations first); 0, the default of every shipped preset,
    starts from a random policy. Not part of the paper's method or of ML-Agents; it exists to
    separate exploration from the reward in the GAIL baseline (a GAIL policy started from the
    demonstrated behaviour: ``bench/gail_variants/gail_bc_init.yaml``,
    docs/reports/gail_baseline.md "GAIL at 2M steps"). A run continued with ``train --resume``
    does not pass again."""

    def __post_init__(self) -> None:
        _check(0 <= self.strength <= 10, 'bc.strength', 'in [0, 10]', self.strength)
        _check(1 <= self.batch_size <= 1_000_000, 'bc.batch_size', 'in [1, 1e6]',
               self.batch_size)
        _check(1 <= self.num_epoch <= 100, 'bc.num_epoch', 'in [1, 100]', self.num_epoch)
        _check(self.steps >= 0, 'bc.steps', '>= 0', self.steps)
        _check(self.schedule in BC_SCHEDULES, 'bc.schedule', f'one of {list(BC_SCHEDULES)}',
               self.schedule)
        _check(0 <= self.pretrain_epochs <= 1000, 'bc.pretrain_epochs', 'in [0, 1000]',
               self.pretrain_epochs)


@dataclass(frozen=True)
class CurriculumConfig:
    """Lessons that lower theta_max when a measure passes a threshold."""

    theta_max_deg: tuple[float, ...] = ()
    """theta_max of each lesson in degrees, non-increasing; empty disables the curriculum."""
    measure: str = 'reward'
    """``reward`` (mean episode extrinsic reward) or ``success`` (success rate)."""
    thresholds: tuple[float, ...] = ()
    """Measure to pass to leave lesson i (len = lessons - 1)."""
    min_lesson_length: int = 100
    """Episodes completed in a lesson before its measure is judged (and the window size)."""

    def __post_init__(self) -> None:
        n = len(self.theta_max_deg)
        _check(all(0 < t <= 180 for t in self.theta_max_deg), 'curriculum.theta_max_deg',
               'values in (0, 180]', self.theta_max_deg)
        _check(all(a >= b for a, b in zip(self.theta_max_deg, self.theta_max_deg[1:],
                                           strict=False)),
               'curriculum.theta_max_deg', 'non-increasing', self.theta_max_deg)
        _check(self.measure in ('reward', 'success'), 'curriculum.measure',
               "'reward' or 'success'", self.measure)
        _check(len(self.thresholds) == max(n - 1, 0), 'curriculum.thresholds',
               f'{max(n - 1, 0)} values (one per lesson change)', self.thresholds)
        _check(self.min_lesson_length >= 1, 'curriculum.min_lesson_length', '>= 1',
               self.min_lesson_length)


@dataclass(frozen=True)
class PopulationConfig:
    """Training across the anatomy population (:mod:`cgail_sim.population`); the
    training env is a :class:`~cgail_learning.envs.PopulationVecEnv`."""

    anatomies: int = 0
    """Training anatomies: the first ``anatomies`` population training seeds
    (:data:`~cgail_sim.population.TRAINING_SEEDS`); 0 trains on ``--anatomy`` alone."""
    redraw_every: int = 4
    """Episodes a worker runs in one anatomy before it draws another from the pool."""
    eval_anatomies: int = 5
    """Anatomies of the periodic evaluation that picks ``best.pt``: the training seeds right
    after the pool (never trained on, never held out)."""
    include: tuple[str, ...] = ()
    """Named anatomies added to the pool beside the population samples, each drawn
    ``include_weight`` times as often as one sample: the built-in ones (``default``,
    ``elongated``) and real aortas (``avt-<case>``, :data:`cgail_sim.anatomy_spec.REAL_NAMES`;
    never one of :data:`~cgail_sim.anatomy_spec.REAL_HELD_OUT`, the generalist's zero-shot
    test set). They lie outside the
    population's ranges in places (``elongated``: root tilt 15 deg, below the population's
    18 deg) and are the anatomies a user tries first, so the generalist trains on them too; its
    evaluation on them uses target sets it never trained on."""
    include_weight: float = 1.0
    """How many times as often a worker draws each ``include`` anatomy as one population
    sample (>= 1). At 1 a built-in gets 1/130 of a 128-sample pool's episodes, too few for
    ``elongated``, which lies farthest outside the population (the generalist trained so:
    0 % there, 92 % on held-out samples)."""

    eval_include: bool = False
    """Whether the periodic evaluation that picks ``best.pt`` also runs the ``include``
    anatomies (with targets drawn from the evaluation episodes' seeds, never the test target
    sets), one episode in every ``eval_anatomies + len(include)``. Without it ``best.pt``
    follows the selection anatomies alone and can land where a built-in is forgotten (the third
    generalist run: ``elongated`` 93-100 % from 2.0M to 3.9M steps, 27 % at 7M, while the
    selection anatomies stayed at 90-100 %)."""

    def __post_init__(self) -> None:
        _check(0 <= self.anatomies <= 1000, 'population.anatomies', 'in [0, 1000]',
               self.anatomies)
        _check(self.redraw_every >= 1, 'population.redraw_every', '>= 1', self.redraw_every)
        _check(1 <= self.eval_anatomies <= 100, 'population.eval_anatomies', 'in [1, 100]',
               self.eval_anatomies)
        if self.include:
            from cgail_sim.anatomy_spec import REAL_HELD_OUT, TRAINING_NAMES

            _check(all(n in TRAINING_NAMES for n in self.include)
                   and len(set(self.include)) == len(self.include), 'population.include',
                   f'distinct names of built-in or real training anatomies '
                   f'{list(TRAINING_NAMES)} (the held-out real ones, {list(REAL_HELD_OUT)}, '
                   'never train)', list(self.include))
        _check(1.0 <= self.include_weight <= 1000.0, 'population.include_weight',
               'in [1, 1000]', self.include_weight)
        _check(not self.eval_include or bool(self.include), 'population.eval_include',
               'false without population.include', self.eval_include)
        _check(not self.include or self.anatomies > 0, 'population.include',
               'no anatomies without a population (population.anatomies > 0)',
               list(self.include))

    @property
    def enabled(self) -> bool:
        """Whether the run trains on the population."""
        return self.anatomies > 0

    def seeds(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """``(training seeds, periodic-evaluation seeds)``: consecutive population training
        seeds from 0, disjoint."""
        from cgail_sim.population import split_seeds

        both = split_seeds('train', self.anatomies + self.eval_anatomies)
        return both[:self.anatomies], both[self.anatomies:]


@dataclass(frozen=True)
class TrainConfig:
    """A whole training run (one preset)."""

    name: str = 'custom'
    """Preset name, recorded in checkpoints and the ONNX metadata."""
    max_steps: int = 500_000
    """Environment steps (all parallel envs together) of the run."""
    num_envs: int = 8
    """Parallel simulator instances (batched env)."""
    network: NetworkConfig = field(default_factory=NetworkConfig)
    """Policy/value network."""
    ppo: PPOConfig = field(default_factory=PPOConfig)
    """PPO settings."""
    extrinsic: RewardSignalConfig = field(
        default_factory=lambda: RewardSignalConfig(strength=1.0))
    """Environment reward signal."""
    gail: GailConfig = field(default_factory=GailConfig)
    """GAIL reward signal; strength 0 disables it."""
    curiosity: CuriosityConfig = field(default_factory=CuriosityConfig)
    """Curiosity reward signal; strength 0 disables it."""
    bc: BCConfig = field(default_factory=BCConfig)
    """Behavioural cloning."""
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    """theta_max curriculum."""
    normalize: bool = True
    """Running mean/std observation normaliser (ML-Agents ``normalize``)."""
    eval_every: int = 20_480
    """Environment steps between periodic evaluations (0 = never)."""
    eval_episodes: int = 15
    """Episodes per periodic evaluation (deterministic policy)."""
    checkpoint_every: int = 51_200
    """Environment steps between checkpoints (0 = only the final one)."""
    env_options: str = 'ours'
    """The simulator's option set (:data:`cgail_sim.config.OPTION_SETS`): ``ours``
    (the default) or ``paper_code`` (the authors' observation, insertion, reward and heartbeat);
    the training, evaluation and demonstration-replay envs all use it."""
    population: PopulationConfig = field(default_factory=PopulationConfig)
    """Training across the anatomy population (off by default)."""

    def __post_init__(self) -> None:
        from cgail_sim.config import OPTION_SETS  # (the simulator owns the names)

        _check(self.env_options in OPTION_SETS, 'env_options', f'one of {sorted(OPTION_SETS)}',
               self.env_options)
        _check(self.max_steps >= 1, 'max_steps', '>= 1', self.max_steps)
        _check(1 <= self.num_envs <= 256, 'num_envs', 'in [1, 256]', self.num_envs)
        _check(self.extrinsic.strength + self.gail.strength + self.curiosity.strength > 0,
               'extrinsic/gail/curiosity strength', 'positive for at least one signal',
               0.0)
        _check(self.eval_every >= 0, 'eval_every', '>= 0', self.eval_every)
        _check(self.eval_episodes >= 1, 'eval_episodes', '>= 1', self.eval_episodes)
        _check(self.checkpoint_every >= 0, 'checkpoint_every', '>= 0', self.checkpoint_every)

    @property
    def needs_demos(self) -> bool:
        """Whether GAIL or BC (in the loop or as a warm start) is active (demonstrations
        required)."""
        return self.gail.strength > 0 or self.bc.strength > 0 or self.bc.pretrain_epochs > 0

    def signals(self) -> dict[str, RewardSignalConfig]:
        """Active reward signals in a fixed order (extrinsic, gail, curiosity)."""
        out: dict[str, RewardSignalConfig] = {}
        for name in ('extrinsic', 'gail', 'curiosity'):
            sig: RewardSignalConfig = getattr(self, name)
            if sig.strength > 0:
                out[name] = sig
        return out


def _build(cls: type, data: Any, prefix: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f'{prefix or "config"} must be a mapping, found {data!r}')
    known = {f.name: f for f in fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        path = f'{prefix}{key}'
        if key not in known:
            raise ConfigError(f'unknown key {path!r}; allowed: {sorted(known)}')
        default = getattr(cls(), key) if key != 'name' else ''
        if is_dataclass(default):
            kwargs[key] = _build(type(default), value, path + '.')
            continue
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif isinstance(default, float):
            ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(
                float(value))
            value = float(value) if ok else value
        elif isinstance(default, tuple) and 'str' in str(known[key].type):
            ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
            value = tuple(value) if ok else value
        elif isinstance(default, tuple):
            ok = isinstance(value, list) and all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in value)
            value = tuple(float(v) for v in value) if ok else value
        else:
            ok = isinstance(value, str)
        if not ok:
            raise ConfigError(f'{path} must be of type {type(default).__name__}, found {value!r}')
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        msg = str(exc)
        if prefix and not msg.startswith(prefix.split('.')[0]):
            msg = prefix + msg
        raise ConfigError(msg) from None


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """Build a validated :class:`TrainConfig` from a nested mapping (YAML content)."""
    cfg: TrainConfig = _build(TrainConfig, data, '')
    return cfg


def load_config(preset_or_path: str | Path) -> TrainConfig:
    """Load a preset by name (``cgail``, ``gail``, ``mu0``...) or a YAML file path.

    Raises:
        ConfigError: unknown preset, unreadable YAML, unknown key or out-of-range value.
    """
    path = Path(preset_or_path)
    if not path.suffix:
        path = PRESET_DIR / f'{preset_or_path}.yaml'
    if not path.is_file():
        names = sorted(p.stem for p in PRESET_DIR.glob('*.yaml'))
        raise ConfigError(f'expected a preset name in {names} or a YAML file, found '
                          f'{str(preset_or_path)!r}')
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f'{path}: invalid YAML: {exc}') from None
    data = dict(data or {})
    data.setdefault('name', path.stem)
    return config_from_dict(data)


def config_to_dict(cfg: Any) -> Any:
    """Plain nested dict of a config (for checkpoints and logs). A field marked
    ``omit_default`` is left out while it has its default (a field added after checkpoints
    were written: their configs and this one's still compare equal on ``--resume``)."""
    if is_dataclass(cfg):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in fields(cfg)
                if not (f.metadata.get('omit_default') and getattr(cfg, f.name) == f.default)}
    if isinstance(cfg, tuple):
        return list(cfg)
    return cfg
