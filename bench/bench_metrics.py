#!/usr/bin/env python3
"""Offline metrics speed: seconds of trial evaluated per second of compute (target >= 100x).

    scripts/ws python bench/bench_metrics.py [--minutes 3] [--rate 40] [--repeat 5]

Writes a synthetic trial bag (tip poses at --rate Hz for --minutes, with 0.5 mm EM noise, a
100-waypoint planned path replanned twice, a goal) to a temporary directory, then times
reading + decoding it (rosbags typestore) and computing the metrics, and prints the ratio of the
trial's duration to the best wall time over --repeat runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import tempfile
import time
from typing import Any

import numpy as np

from cgail_bags.bagio import BagWriter, TYPESTORE
from cgail_bags.qos import COMMAND, LATCHED, SENSOR
from cgail_bags.reader import read_trial
from cgail_planner.core.metrics import compute_trial_metrics

T = TYPESTORE.types
T0 = 1_700_000_000 * 10**9


def header(ns: int) -> Any:
    return T['std_msgs/msg/Header'](
        stamp=T['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9),
        frame_id='phantom')


def pose(ns: int, xyz: np.ndarray) -> Any:
    return T['geometry_msgs/msg/PoseStamped'](header=header(ns), pose=T['geometry_msgs/msg/Pose'](
        position=T['geometry_msgs/msg/Point'](x=float(xyz[0]), y=float(xyz[1]),
                                              z=float(xyz[2])),
        orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)))


def make_bag(path: Path, minutes: float, rate: float) -> int:
    rng = np.random.default_rng(0)
    s = np.linspace(0.0, 1.0, 100)
    centre = np.column_stack([0.06 * np.cos(np.pi * s), 0.06 * np.sin(np.pi * s), 0.2 * s])
    count = int(minutes * 60 * rate)
    u = np.linspace(0.0, 1.0, count)
    tip = np.column_stack([0.062 * np.cos(np.pi * u), 0.062 * np.sin(np.pi * u), 0.2 * u])
    tip += rng.normal(0.0, 0.0005, tip.shape)
    ser = TYPESTORE.serialize_cdr
    with BagWriter(path, custom_data={'condition': 'bench'}) as w:
        w.add_topic('/planner/goal', 'geometry_msgs/msg/PoseStamped', [COMMAND])
        w.add_topic('/planner/path', 'nav_msgs/msg/Path', [LATCHED])
        w.add_topic('/em_tracker/tip_pose', 'geometry_msgs/msg/PoseStamped', [SENSOR])
        w.write('/planner/goal', T0 - 10**9,
                ser(pose(T0 - 10**9, centre[-1]), 'geometry_msgs/msg/PoseStamped'))
        period = round(1e9 / rate)
        replans = {0: 0.0, count // 3: 0.001, 2 * count // 3: -0.001}
        for k in range(count):
            ns = T0 + k * period
            if k in replans:
                shifted = centre + replans[k]
                msg = T['nav_msgs/msg/Path'](header=header(ns - 1),
                                             poses=[pose(ns - 1, q) for q in shifted])
                w.write('/planner/path', ns - 1, ser(msg, 'nav_msgs/msg/Path'))
            w.write('/em_tracker/tip_pose', ns,
                    ser(pose(ns, tip[k]), 'geometry_msgs/msg/PoseStamped'))
    return count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--minutes', type=float, default=3.0)
    parser.add_argument('--rate', type=float, default=40.0)
    parser.add_argument('--repeat', type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / 'bench_trial'
        count = make_bag(bag, args.minutes, args.rate)
        size = sum(f.stat().st_size for f in bag.iterdir())
        reads, computes = [], []
        for _ in range(args.repeat):
            start = time.perf_counter()
            trial = read_trial(bag)
            mid = time.perf_counter()
            metrics = compute_trial_metrics(trial)
            reads.append(mid - start)
            computes.append(time.perf_counter() - mid)
    duration = count / args.rate
    total = min(np.add(reads, computes))
    print(f'trial: {duration:.0f} s, {count} tip poses at {args.rate:g} Hz, 3 paths x 100 '
          f'waypoints, bag {size / 1024:.0f} kB')
    print(f'read+decode: best {min(reads) * 1e3:.1f} ms, median {np.median(reads) * 1e3:.1f} ms')
    print(f'metrics:     best {min(computes) * 1e3:.1f} ms, '
          f'median {np.median(computes) * 1e3:.1f} ms')
    print(f'T_r mean {metrics.tracking_mean * 1e3:.2f} mm, T_a {metrics.targeting_error * 1e3:.2f}'
          f' mm, curvature {metrics.curvature_mean * 1e-3:.3f} mm^-1')
    print(f'speed: {duration / total:.0f}x real time (best of {args.repeat}; target >= 100x)')


if __name__ == '__main__':
    main()
