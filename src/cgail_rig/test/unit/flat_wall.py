"""A flat wall for the phantom physics tests: the plane z = 2 mm, the lumen below."""

from __future__ import annotations

import numpy as np


class FlatWall:
    """Wall plane z = 0.002 with the lumen below (outward normal +z)."""

    def reset(self) -> None:
        pass

    def tip_contact(self, tip, radius, dt):
        from cgail_sim.contact import Contact

        depth = tip[2] + radius - 0.002
        pen = max(depth, 0.0)
        return Contact(penetration=pen, force=0.0, normal=np.array([0.0, 0.0, 1.0]),
                       in_contact=pen > 0, clearance=max(-depth, 0.0))
