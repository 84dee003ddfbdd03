"""Tip-frame maths of the internal view (numpy only).

Tip frame conventions are those of :mod:`cgail_sim.ftl_model`: the columns of the tip
rotation ``R`` are ``x_A, y_A, z_A`` in ``phantom``; the catheter heads along ``y_A``; a bend
``[alpha, gamma]`` turns the heading to ``Rx(alpha) Rz(gamma) e_y = (-sin g, cos g cos a,
cos g sin a)`` (tip frame). The internal view looks along ``y_A`` with ``z_A`` up, so screen right
is ``x_A``: a point ``d`` (tip frame) appears at ``(d_x, d_z)`` and the suggested bend points to
``(-sin g, cos g sin a)`` on screen.
"""

from __future__ import annotations

import math

import numpy as np


def to_tip_frame(rotation: np.ndarray, tip: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(3,) ``point`` (phantom) expressed in the tip frame."""
    return np.asarray(rotation).T @ (np.asarray(point, dtype=float) - np.asarray(tip))


def off_heading(d_tip: np.ndarray) -> tuple[float, float, float]:
    """Where a tip-frame direction lies relative to the heading.

    Returns:
        ``(angle, screen_x, screen_y)``: the angle between ``d`` and the heading ``y_A`` (rad,
        0..pi) and the unit direction of ``d`` on the internal-view screen (right = ``x_A``,
        up = ``z_A``; ``(0, 0)`` when ``d`` is along the heading or zero).
    """
    d = np.asarray(d_tip, dtype=float)
    lateral = math.hypot(d[0], d[2])
    angle = math.atan2(lateral, d[1])
    if lateral < 1e-12:
        return angle, 0.0, 0.0
    return angle, d[0] / lateral, d[2] / lateral


def bend_on_screen(alpha: float, gamma: float) -> tuple[float, float, float]:
    """The suggested bend as seen in the internal view.

    Returns:
        ``(magnitude, screen_x, screen_y)``: the angle between the current and the bent heading
        ``acos(cos(alpha) cos(gamma))`` (rad) and its unit screen direction
        ``(-sin g, cos g sin a)`` normalised (``(0, 0)`` for no bend).
    """
    heading = np.array([-math.sin(gamma), math.cos(gamma) * math.cos(alpha),
                        math.cos(gamma) * math.sin(alpha)])
    return off_heading(heading)


def ray_directions(rotation: np.ndarray, count: int, cone: float) -> np.ndarray:
    """(count + 1, 3) unit rays in phantom: the heading, then ``count`` on a cone around it.

    The cone rays are at angle ``cone`` from the heading, evenly spread in azimuth starting at
    ``+x_A`` (screen right) and going towards ``+z_A`` (screen up).
    """
    r = np.asarray(rotation, dtype=float)
    az = 2.0 * np.pi * np.arange(count) / max(count, 1)
    local = np.stack([np.sin(cone) * np.cos(az), np.full(count, np.cos(cone)),
                      np.sin(cone) * np.sin(az)], axis=1)
    dirs = np.vstack([[0.0, 1.0, 0.0], local]) @ r.T
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
