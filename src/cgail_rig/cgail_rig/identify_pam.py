"""``cgail identify-pam``: identify the PAM controller's bending model on the bench.

    cgail identify-pam --sim --plant-seed 3 --out runs/identify_s3
    cgail identify-pam --bag runs/bench_bag --out runs/identify_rig

**Bench.** The catheter is clamped at the base of its steerable segment, in free air, with the
EM sensor at the tip; the insertion is held. ``--sim`` builds that rig on a lockstep executor
(:mod:`cgail_rig.lockstep`) from the nodes of ``launch/sim_rig.launch.yaml``: the
``phantom`` with ``fixture: bench`` (the tip is the arc of the true plant's bend, through the
simulated Aurora with its EM noise), ``aurora`` and ``pam_controller``, the way ``cgail session``
runs its trials' rigs: messages in-process (the executor's ``transport='inprocess'``: the bytes
DDS would carry, in DDS's order) and the Aurora node's Combined API commands answered by the
simulated Aurora in its polling call (``link: in_process``), the same bag as through DDS and the
pty, in a fraction of the time. It runs the scripted
excitation (:mod:`pam_controller.core.identification`: vented rest, triangular sweeps of
growing amplitude per axis, a multisine on both) and records ``em_tracker/tip_pose``,
``pam/pressures`` (and the commands and the true pose) to ``<out>/bench_bag``. On a real rig,
run the same excitation and record the same topics, then ``--bag``.

**Commands.** ``pam_node`` takes bend commands only. For the excitation it runs with a linear
model without hysteresis (:data:`EXCITATION_PAM_PARAMETERS`: ``hysteresis_fraction`` 0, gain
1e-6 rad/Pa), so its inverse is exactly ``dp = bend / gain``: a bend command of ``1e-6 dp``
is a differential-pressure command ``dp`` around the bias, through the node's own slew limit,
watchdog and pressure caps. The fit reads the measured pressures, never the commands.

**Fit.** The bend is read from the EM orientation relative to the base (measured while the
chambers are vented), the controller's parameters that ``pam_controller.yaml`` exposes (the
hysteresis, a bend offset and a gain per axis, the cross-coupling) are fitted by bounded least
squares on the sweeps, and the multisine is held out. Written to
``<out>``: ``pam_identified.yaml`` (every key of ``pam_controller.yaml``, the identified ones
replaced; ``pam_node --ros-args --params-file``), ``loops.png`` (measured bend against
differential pressure per axis, with the nominal and the identified model) and ``report.md``.

Why here and not in pam_controller: the fit itself is pure and lives there
(``pam_controller.core.identification``), but the simulated bench needs the phantom and the
bags need the recorder and reader, both of this package, and pam_controller must not depend
on cgail_planner (cgail_planner depends on it).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator, Mapping, Sequence
import contextlib
import ctypes
from dataclasses import asdict
import gc
import math
import os
from pathlib import Path
import shutil
import sys
import tempfile
import time
from typing import Any

import numpy as np

from cgail_sim.cli_help import tool_parser

#: Recorded on the bench: what the fit reads (the first two), the commands and the true pose.
TOPICS = ('em_tracker/tip_pose', 'pam/pressures', 'catheter/bend_command', 'phantom/tip_pose')
#: The topics a bag must hold for the fit.
FIT_TOPICS = ('em_tracker/tip_pose', 'pam/pressures')
#: Bend command per Pa of differential pressure of the excitation's linear pam_node, rad/Pa:
#: the 90 deg bend cap then allows 1.57 MPa, above any differential the pressures reach.
COMMAND_GAIN_RAD_PER_PA = 1e-6
#: pam_controller parameters of the excitation (module docstring).
EXCITATION_PAM_PARAMETERS: dict[str, Any] = {
    'hysteresis_fraction': 0.0, 'hysteresis_gain_rad_per_pa': COMMAND_GAIN_RAD_PER_PA}
#: Lockstep tick of the simulated bench, Hz (the session's: one tick per Aurora frame).
PHYSICS_RATE_HZ = 40.0
#: The bench's nodes (of the launch file): the phantom as the bench fixture, the tracker, the
#: PAM controller.
BENCH_NODES = ('phantom', 'aurora', 'pam_controller')
#: Simulated seconds between two sweeps of the bench for what reached it from outside (the
#: session's ``SWEEP_S``): nothing outside talks to the bench.
SWEEP_S = 0.25
#: ros-args of the bench's context: node logs to the log file only.
ROS_ARGS = ['--ros-args', '--disable-stdout-logs', '--disable-rosout-logs']


class BenchError(RuntimeError):
    """The simulated bench could not run (a node failed, the recorder found no topics)."""


def pam_config_file() -> Path:
    """``config/pam_controller.yaml`` of pam_controller (source tree or install share)."""
    import pam_controller

    here = Path(pam_controller.__file__).resolve().parents[1] / 'config' / 'pam_controller.yaml'
    if here.is_file():
        return here
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        cand = Path(prefix) / 'share' / 'pam_controller' / 'config' / 'pam_controller.yaml'
        if prefix and cand.is_file():
            return cand
    return here


# ---------------------------------------------------------------------- the simulated bench
def run_bench(bag: Path, *, plant: str = 'true', plant_seed: int = 0, seed: int = 0,
              excitation: Any = None, domain_id: int, launch_file: Path | None = None) -> dict:
    """Run the excitation on the simulated bench and record it to ``bag``.

    Args:
        bag: bag directory to create.
        plant: the phantom's plant (``'true'``, ``'nominal'``, ``'ideal'``).
        plant_seed: seed of the true plant's draw.
        seed: seed of the EM noise.
        excitation: an :class:`~pam_controller.core.identification.ExcitationConfig`
            (default: the full one).
        domain_id: the ROS domain of the bench.
        launch_file: rig launch YAML (default: the package's ``sim_rig.launch.yaml``).

    Returns:
        Recorded messages per topic.
    """
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Header

    from cgail_bags.record import BagRecorder, RecorderConfig
    from cgail_planner.nodes import conversions as conv
    from cgail_rig.launch_spec import default_launch_file, load_launch_file
    from cgail_rig.launcher import build_node
    from cgail_rig.lockstep import LockstepExecutor
    from pam_controller.core import identification as idf

    exc_cfg = excitation if excitation is not None else idf.ExcitationConfig()
    dt = 1.0 / PHYSICS_RATE_HZ
    schedule = idf.excitation_schedule(exc_cfg, dt)
    context = rclpy.Context()
    rclpy.init(args=ROS_ARGS, context=context, domain_id=domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    tmp = tempfile.mkdtemp(prefix='cgail_bench_')
    nodes: dict[str, Any] = {}
    recorder = None
    session = None
    try:
        # the session's cheap paths (TrialRig): messages between the bench's nodes in-process
        # (the same bytes DDS would carry, the same delivery order), the simulated Aurora
        # answering the aurora node in its polling call; the same nodes and the same data
        executor = LockstepExecutor(period_s=dt, transport='inprocess',
                                    sweep_every=max(1, round(SWEEP_S * PHYSICS_RATE_HZ)))
        link = str(Path(tmp) / 'aurora')
        overrides = {
            'phantom': {'fixture': 'bench', 'lockstep': True, 'aurora_link': link,
                        'seed': seed, 'plant': plant, 'plant_seed': plant_seed,
                        'physics_rate_hz': PHYSICS_RATE_HZ, 'simulate_driver': False,
                        'marker_rate_hz': 0.1},
            'aurora': {'port': link, 'rate_hz': PHYSICS_RATE_HZ, 'poll_mode': 'clock',
                       'link': 'in_process'},
            'pam_controller': {'control_rate_hz': PHYSICS_RATE_HZ / 2.0,
                               **EXCITATION_PAM_PARAMETERS},
        }
        launch = load_launch_file(Path(launch_file or default_launch_file()))
        for spec in launch.nodes:
            if spec.name in overrides:
                nodes[spec.name] = build_node(spec, overrides[spec.name], lean=True,
                                              context=context, prepare=executor.add_node)
        missing = sorted(set(overrides) - set(nodes))
        if missing:
            raise BenchError(f'expected nodes {sorted(overrides)} in the launch file, found '
                             f'{sorted(nodes)} (missing {missing})')
        executor.add_hook(nodes['phantom'].advance)
        session = rclpy.create_node('identify_pam', context=context,
                                    start_parameter_services=False, enable_rosout=False)
        executor.add_node(session)
        command_pub = session.create_publisher(JointState, 'catheter/bend_command',
                                               conv.COMMAND_QOS)
        recorder = BagRecorder(session, RecorderConfig(output=bag, topics=TOPICS,
                                                       condition='identify_pam'))
        deadline = time.monotonic() + 30.0
        while len(recorder.topics) < len(TOPICS):
            if time.monotonic() > deadline:
                raise BenchError(f'expected the recorder to find {list(TOPICS)} within 30 s, '
                                 f'found {recorder.topics}')
            time.sleep(0.01)
            recorder.discover()
        executor.seal()
        from pam_controller.core.bending_model import BEND_JOINT_NAMES

        end = schedule.t[-1] + 0.5
        while executor.now_s < end:
            executor.tick()
            dp, segment = schedule.at(executor.now_s)
            if segment != idf.REST:  # the rest: nothing commanded, the watchdog vents
                command_pub.publish(JointState(
                    header=Header(stamp=session.get_clock().now().to_msg()),
                    name=list(BEND_JOINT_NAMES),
                    position=[float(v) for v in COMMAND_GAIN_RAD_PER_PA * dp]))
        if executor.errors:
            raise BenchError(f'callback error on the bench: {executor.errors[0]}')
    finally:
        counts: dict[str, int] = {}
        if recorder is not None:
            recorder.stop()
            counts = dict(recorder.counts)
        for node in [*reversed(list(nodes.values())), session]:
            if node is not None:
                node.destroy_node()
        nodes.clear()
        rclpy.try_shutdown(context=context)
        gc.collect()
        context.destroy()
        shutil.rmtree(tmp, ignore_errors=True)
    return counts


# ---------------------------------------------------------------------- the bag
def read_bench_bag(bag: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(pressure_t, pressures (T, 4), pose_t, rotations (K, 3, 3))`` of a bench bag.

    Times are the bag's log times (the recorder's clock: ``pam/pressures`` has no stamp).

    Raises:
        BagError: unreadable bag, or a topic of :data:`FIT_TOPICS` missing.
    """
    from scipy.spatial.transform import Rotation

    from cgail_bags.bagio import iter_raw, open_bag, TYPESTORE
    from cgail_bags.errors import BagError
    from cgail_bags.reader import topic_matches

    pt: list[float] = []
    pv: list[list[float]] = []
    et: list[float] = []
    quats: list[tuple[float, float, float, float]] = []
    with open_bag(bag) as reader:
        roles: dict[str, str] = {}
        for conn in reader.connections:
            for want in FIT_TOPICS:
                if topic_matches(conn.topic, want):
                    roles[conn.topic] = want
        missing = [t for t in FIT_TOPICS if t not in roles.values()]
        if missing:
            found = sorted(c.topic for c in reader.connections)
            raise BagError(f'{bag}: expected topics {list(FIT_TOPICS)} for identify_pam, found '
                           f'{found} (missing {missing})')
        for conn, log_ns, raw in iter_raw(reader, topics=list(roles)):
            msg: Any = TYPESTORE.deserialize_cdr(raw, conn.msgtype)
            if roles[conn.topic] == 'pam/pressures':
                if len(msg.data) == 4:
                    pt.append(log_ns * 1e-9)
                    pv.append([float(v) for v in msg.data])
            else:
                q = msg.pose.orientation
                et.append(log_ns * 1e-9)
                quats.append((q.x, q.y, q.z, q.w))
    rot = Rotation.from_quat(np.array(quats).reshape(-1, 4)).as_matrix() if quats \
        else np.zeros((0, 3, 3))
    return (np.array(pt), np.array(pv).reshape(-1, 4), np.array(et), rot)


# ---------------------------------------------------------------------- outputs
def parameters_yaml(template: str, values: Mapping[str, float], header: Sequence[str]) -> str:
    """``pam_controller.yaml`` with ``values`` replacing its keys' values, comments kept and
    ``header`` lines (comments) on top.

    Raises:
        ValueError: a key of ``values`` is not in the template.
    """
    lines = template.splitlines()
    done: set[str] = set()
    for i, line in enumerate(lines):
        key = line.strip().split(':', 1)[0]
        if key in values and not line.lstrip().startswith('#'):
            indent = line[:len(line) - len(line.lstrip())]
            lines[i] = f'{indent}{key}: {values[key]!r}'
            done.add(key)
    missing = sorted(set(values) - done)
    if missing:
        raise ValueError(f'expected the keys {missing} in pam_controller.yaml, found them '
                         'missing')
    return '\n'.join([f'# {h}' for h in header] + lines) + '\n'


def loops_png(data: Any, result: Any, path: Path, title: str) -> Path:
    """Measured bend vs differential pressure per axis (sweeps and multisine), with the nominal
    and the identified model's prediction on the same pressures."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from pam_controller.core.identification import predict

    nominal = predict(result.nominal, data.dp)
    identified = predict(result.config, data.dp)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.5), sharex='col')
    for col, name in enumerate(('alpha', 'gamma')):
        for row, (mask, part) in enumerate(((data.fit, 'sweeps (fitted)'),
                                            (data.validation, 'multisine (held out)'))):
            ax = axes[row, col]
            if not np.any(mask):
                ax.set_axis_off()
                continue
            x = data.dp[mask, col] / 1e3
            ax.plot(x, np.degrees(data.bend[mask, col]), color='k', lw=1.4,
                    label='measured (EM)')
            ax.plot(x, np.degrees(nominal[mask, col]), color='tab:red', lw=0.9, ls='--',
                    label='nominal model')
            ax.plot(x, np.degrees(identified[mask, col]), color='tab:blue', lw=0.9,
                    label='identified model')
            ax.set_title(f'{name}: {part}')
            ax.grid(alpha=0.3)
            ax.set_ylabel(f'bend {name}, deg')
            if row == 1 or not np.any(data.validation):
                ax.set_xlabel(f'differential pressure dp_{name}, kPa')
    axes[0, 0].legend(loc='upper left', fontsize=8)
    e = result.errors
    deg = {m: {k: math.degrees(v) for k, v in e[m].items()} for m in e}
    fig.suptitle(f'{title}\nRMS bend error, sweeps / multisine: nominal '
                 f'{deg["nominal"]["fit"]:.2f} / {deg["nominal"]["validation"]:.2f} deg, '
                 f'identified {deg["identified"]["fit"]:.2f} / '
                 f'{deg["identified"]["validation"]:.2f} deg', fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def report_text(result: Any, data: Any, source: str, extra: Sequence[str] = ()) -> str:
    """The markdown report: errors (rad and deg), parameters nominal vs identified."""
    from pam_controller.core.identification import identified_parameters

    e = result.errors
    lines = ['# identify_pam', '', f'Data: {source}.', '',
             f'{int(np.count_nonzero(data.fit))} sweep samples (fitted), '
             f'{int(np.count_nonzero(data.validation))} multisine samples (held out), '
             f'{data.t.size} in all.', '', '## RMS bend error', '',
             '| model | sweeps (fit) | multisine (held out) | all |', '|---|---|---|---|']
    for model in ('nominal', 'identified'):
        cells = [f'{e[model][p]:.4f} rad ({math.degrees(e[model][p]):.2f} deg)'
                 if math.isfinite(e[model][p]) else '-' for p in ('fit', 'validation', 'all')]
        lines.append(f'| {model} | ' + ' | '.join(cells) + ' |')
    lines += ['', f'Identified / nominal (all samples): {result.improvement:.2f}.', '',
              '## Parameters', '', '| parameter | nominal | identified |', '|---|---|---|']
    nom, ide = identified_parameters(result.nominal), identified_parameters(result.config)
    lines += [f'| `{k}` | {nom[k]:.6g} | {ide[k]:.6g} |' for k in nom]
    hyst, hyst_nom = result.config.hysteresis, result.nominal.hysteresis
    lines += ['', f'`hysteresis_play_count` kept at {hyst.play_count}; major loop width '
              f'nominal {hyst_nom.major_loop_width():.3f} rad, identified '
              f'{hyst.major_loop_width():.3f} rad. The model: per axis a Prandtl-Ishlinskii '
              'operator `h = PI[dp]`, then `bend = b0 + K h`, `b0` the `bend_offset_*`, `K = '
              '[[gain_scale_alpha, coupling_alpha_from_gamma], [coupling_gamma_from_alpha, '
              'gain_scale_gamma]]`.', '',
              '## Not representable', '',
              'The controller\'s model has no lag term. A first-order lag after the identified '
              f'model, fitted on the sweeps, is {result.lag_s:.3f} s (the slow sweeps see little '
              'of a lag: an estimate from below); with it the RMS bend error would be '
              + ', '.join(f'{math.degrees(result.lag_errors[part]):.2f} deg ({label})'
                          for part, label in (('fit', 'sweeps'), ('validation', 'multisine'),
                                              ('all', 'all'))
                          if math.isfinite(result.lag_errors.get(part, math.nan)))
              + '. Also left in the residual: the dead zone (the offset holds around the bias, '
              'not vented) and the shape of the plant\'s own loops.']
    lines += list(extra)
    return '\n'.join(lines) + '\n'


#: (get, set) entry points of the thread count of an OpenBLAS build (numpy's and scipy's wheels
#: prefix theirs), tried in turn.
_OPENBLAS_THREADS = (('scipy_openblas_get_num_threads64_', 'scipy_openblas_set_num_threads64_'),
                     ('scipy_openblas_get_num_threads', 'scipy_openblas_set_num_threads'),
                     ('openblas_get_num_threads64_', 'openblas_set_num_threads64_'),
                     ('openblas_get_num_threads', 'openblas_set_num_threads'))


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Every OpenBLAS loaded in this process (numpy's, scipy's) on one thread inside the block,
    its thread count restored after; nothing where there is none (another BLAS, not Linux).

    The fit's least squares (an SVD of a small Jacobian per step) gains nothing from a second
    BLAS thread, which spins waiting for work: on 2 cores the fit took 0.8 s wall and 1.5 s CPU
    on two threads, 0.73 s and 0.73 s on one, and once 4.9 s on two while the other core was
    busy, as it is in ``cgail session`` (its workers warm up beside the identification). The
    fitted model was the same to the last bit on one thread and on two (plant seeds 0 and 1).
    """
    restore: list[tuple[Any, int]] = []
    try:
        with contextlib.suppress(OSError):
            paths = {line.split()[-1] for line in Path('/proc/self/maps').read_text().splitlines()
                     if 'openblas' in line.rsplit('/', 1)[-1] and '.so' in line}
            for path in sorted(paths):
                lib = ctypes.CDLL(path)
                for get, put in _OPENBLAS_THREADS:
                    if hasattr(lib, get) and hasattr(lib, put):
                        restore.append((getattr(lib, put), int(getattr(lib, get)())))
                        getattr(lib, put)(1)
                        break
        yield
    finally:
        for put, threads in restore:
            put(threads)


def identify_bag(bag: Path, out: Path, *, source: str = '', extra: Sequence[str] = (),
                 plots: list[Callable[[], Path]] | None = None) -> Any:
    """Fit a bench bag and write ``pam_identified.yaml``, ``loops.png``, ``report.md`` to
    ``out``; returns the :class:`~pam_controller.core.identification.FitResult`.

    With ``plots`` (a list), ``loops.png`` is not drawn here: a callable that draws it is
    appended, for a caller that needs the model now and the figure later (``cgail session``
    draws it while its trials run: matplotlib and the figure cost ~1-2 s that would otherwise
    delay every trial).

    Raises:
        BagError: unreadable bag or a topic missing.
        IdentificationError: data that cannot identify the model.
    """
    from pam_controller.core import identification as idf
    from pam_controller.core.bending_model import BendingModelConfig

    pt, p, et, rot = read_bench_bag(bag)
    data = idf.align(pt, p, et, rot)
    model = BendingModelConfig()
    idf.check_excitation(data, model)
    with one_blas_thread():
        result = idf.fit_bending_model(data, model)
    out.mkdir(parents=True, exist_ok=True)
    values = idf.identified_parameters(result.config)
    header = [f'pam_controller parameters identified by identify_pam on {source or bag}.',
              f'RMS bend error: nominal {result.errors["nominal"]["all"]:.4f} rad, identified '
              f'{result.errors["identified"]["all"]:.4f} rad (report.md).']
    (out / 'pam_identified.yaml').write_text(
        parameters_yaml(pam_config_file().read_text(), values, header))
    (out / 'report.md').write_text(report_text(result, data, source or str(bag), extra))

    def draw() -> Path:
        return loops_png(data, result, out / 'loops.png', f'identify_pam: {source or bag.name}')

    if plots is None:
        draw()
    else:
        plots.append(draw)
    return result


def bench_modules(launch_file: Path | None = None) -> None:
    """Import what :func:`run_bench` needs (rclpy, the recorder, the lockstep executor, the
    modules of the bench's nodes), so that :func:`identify_sim` does it while its domain probe
    listens (:func:`~cgail_rig.domain.reserve_domain_during`); touches no ROS domain."""
    import importlib

    import cgail_bags.record  # noqa: F401
    from cgail_rig.launch_spec import default_launch_file, load_launch_file
    import cgail_rig.launcher
    import cgail_rig.lockstep  # noqa: F401

    for spec in load_launch_file(Path(launch_file or default_launch_file())).nodes:
        if spec.name in BENCH_NODES:
            importlib.import_module(spec.plugin.partition(':')[0])


def identify_sim(out: Path, *, plant_seed: int, plant: str = 'true', seed: int = 0,
                 excitation: Any = None, domain_id: int | None = None,
                 plots: list[Callable[[], Path]] | None = None) -> Any:
    """Record the excitation on the simulated bench to ``out/bench_bag`` (on ``domain_id``, or
    a free domain of its own), then :func:`identify_bag` (``plots``: as there)."""
    from cgail_rig.domain import reserve_domain_during
    from pam_controller.core import identification as idf

    bag = out / 'bench_bag'
    if bag.exists():
        shutil.rmtree(bag)
    out.mkdir(parents=True, exist_ok=True)
    lease = None
    if domain_id is None:
        lease, _ = reserve_domain_during(bench_modules)
        domain_id = lease.domain_id
    try:
        run_bench(bag, plant=plant, plant_seed=plant_seed, seed=seed, excitation=excitation,
                  domain_id=domain_id)
    finally:
        if lease is not None:
            lease.release()
    exc_cfg = excitation if excitation is not None else idf.ExcitationConfig()
    extra = ['', '## Excitation', '', f'Simulated bench, plant `{plant}` seed {plant_seed}, EM '
             f'noise seed {seed}: {exc_cfg.duration_s:.0f} s.', '', '```',
             *(f'{k}: {v}' for k, v in asdict(exc_cfg).items()), '```']
    return identify_bag(bag, out, source=f'simulated bench, plant {plant} seed {plant_seed}',
                        extra=extra, plots=plots)


# ---------------------------------------------------------------------- command line
def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail identify-pam``."""
    p = tool_parser('identify-pam', __doc__)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument('--sim', action='store_true',
                     help='run the excitation on the simulated bench (phantom fixture: bench), '
                          'record <out>/bench_bag, fit it')
    src.add_argument('--bag', type=Path, help='fit a recorded bench bag (em_tracker/tip_pose, '
                                              'pam/pressures)')
    p.add_argument('--out', type=Path, required=True,
                   help='output directory (pam_identified.yaml, loops.png, report.md)')
    p.add_argument('--plant-seed', type=int, default=0, help="seed of the true plant's draw")
    p.add_argument('--plant', choices=('true', 'nominal', 'ideal'), default='true',
                   help="the phantom's plant (--sim): true (drawn from its sourced ranges "
                        "with --plant-seed), nominal (its nominal values) or ideal (the PAM "
                        "controller's nominal model)")
    p.add_argument('--seed', type=int, default=0, help='seed of the EM noise (--sim)')
    p.add_argument('--short', action='store_true',
                   help='the short excitation (about 37 s of rig time instead of about 200 s)')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail identify-pam``; returns the exit status."""
    from cgail_bags.errors import BagError
    from cgail_rig.domain import DomainError
    from pam_controller.core import identification as idf

    args = build_parser().parse_args(argv)

    def fail(text: str) -> int:
        print(f'cgail identify-pam: error: {text}', file=sys.stderr)
        return 2

    excitation = idf.SHORT_EXCITATION if args.short else idf.ExcitationConfig()
    try:
        if args.sim:
            if not os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE'):
                return fail('ROS_AUTOMATIC_DISCOVERY_RANGE is unset (DDS would multicast); '
                            'run through scripts/ws')
            os.environ.setdefault('ROS_LOG_DIR', str((args.out / 'logs').resolve()))
            result = identify_sim(args.out, plant_seed=args.plant_seed, plant=args.plant,
                                  seed=args.seed, excitation=excitation)
        else:
            result = identify_bag(args.bag, args.out)
    except (BagError, idf.IdentificationError, DomainError, BenchError) as exc:
        return fail(str(exc))
    e = result.errors
    print(f'cgail identify-pam: RMS bend error nominal {e["nominal"]["all"]:.4f} rad '
          f'({math.degrees(e["nominal"]["all"]):.2f} deg), identified '
          f'{e["identified"]["all"]:.4f} rad ({math.degrees(e["identified"]["all"]):.2f} deg); '
          f'wrote {args.out / "pam_identified.yaml"}, loops.png, report.md')
    return 0


if __name__ == '__main__':
    sys.exit(main())
