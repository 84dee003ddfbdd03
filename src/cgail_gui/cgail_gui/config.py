"""Configuration of the guidance GUI (:class:`GuiConfig`)."""

from __future__ import annotations

from dataclasses import dataclass
import ipaddress
import math

from cgail_sim.ftl_model import CatheterConfig


@dataclass(frozen=True)
class GuiConfig:
    """Everything the GUI server and node need, validated once."""

    host: str = '127.0.0.1'
    """Bind address of the HTTP/WebSocket server (an IPv4/IPv6 literal; loopback by default)."""
    port: int = 8780
    """TCP port, 0..65535 (0: the OS picks a free port; the node logs the URL)."""
    max_rate_hz: float = 60.0
    """Highest rate of state updates sent to one page, Hz, in (0, 240]; updates arriving
    faster are merged (newest value wins), so a 40 Hz tracker is never queued up."""
    mesh_rate_hz: float = 10.0
    """Dynamic mode: highest rate of the deformed-wall frames forwarded from the phantom's
    ``lumen`` marker (``phantom/markers``) to the page, Hz, in (0, 60]; the phantom's
    ``marker_rate_hz`` bounds it too."""
    anatomy: str = 'default'
    """Anatomy shown: a built-in name, a prepared anatomy directory or a mesh file with its
    ``<stem>.yaml`` landmarks (:func:`cgail_sim.anatomy_spec.resolve_anatomy`);
    '' = none."""
    dynamic: bool = False
    """Dynamic mode: the wall drawn and raycast is the phantom's deforming one, taken from its
    ``lumen`` marker on ``phantom/markers`` (the anatomy's rest shape until that arrives)."""
    max_bend_rad: float = CatheterConfig().theta_max
    """Reachable bend of the catheter tip (theta_max), rad, in (0, pi/2]; the internal view
    draws the suggested bend against it."""
    trial_limit_s: float = 180.0
    """Trial time limit, s, > 0 (the paper's 3 minutes)."""
    success_radius_m: float = 0.010
    """Tip-to-target distance that counts as reached (stops the trial timer), m, > 0."""
    stale_after_s: float = 0.5
    """No tip pose for this long: the page shows the tracker as stale, s, > 0."""
    ray_count: int = 8
    """Rays cast around the heading for the wall distance (plus one along it), 0..64."""
    ray_length_m: float = 0.05
    """Length of those rays, m, > 0 (no hit within it is shown as '> length')."""
    ray_cone_rad: float = math.radians(30.0)
    """Angle of the ray cone around the heading, rad, in [0, pi/2]."""
    bags_dir: str = 'bags'
    """Directory whose bags the page may replay (searched recursively, 3 levels); '' = off."""

    def __post_init__(self) -> None:
        try:
            ipaddress.ip_address(self.host)
        except ValueError:
            raise ValueError(f'host must be an IPv4 or IPv6 address literal, '
                             f'found {self.host!r}') from None
        if isinstance(self.port, bool) or not isinstance(self.port, int) \
                or not 0 <= self.port <= 65535:
            raise ValueError(f'port must be an int in [0, 65535], found {self.port!r}')
        _in_range('max_rate_hz', self.max_rate_hz, 0.0, 240.0)
        _in_range('mesh_rate_hz', self.mesh_rate_hz, 0.0, 60.0)
        _in_range('max_bend_rad', self.max_bend_rad, 0.0, math.pi / 2 + 1e-9)
        _positive('trial_limit_s', self.trial_limit_s)
        _positive('success_radius_m', self.success_radius_m)
        _positive('stale_after_s', self.stale_after_s)
        if isinstance(self.ray_count, bool) or not isinstance(self.ray_count, int) \
                or not 0 <= self.ray_count <= 64:
            raise ValueError(f'ray_count must be an int in [0, 64], found {self.ray_count!r}')
        _positive('ray_length_m', self.ray_length_m)
        if not (math.isfinite(self.ray_cone_rad) and 0.0 <= self.ray_cone_rad <= math.pi / 2):
            raise ValueError(f'ray_cone_rad must be in [0, pi/2], found {self.ray_cone_rad}')
        if self.anatomy:
            from cgail_sim.anatomy_spec import check_anatomy_spec

            check_anatomy_spec(self.anatomy)  # (an AnatomyError is a ValueError)

    @property
    def url(self) -> str:
        """The page's address for the configured host and port."""
        host = f'[{self.host}]' if ':' in self.host else self.host
        return f'http://{host}:{self.port}/'


def _in_range(name: str, value: float, low: float, high: float) -> None:
    """Raise unless ``low < value <= high`` and finite."""
    if not (isinstance(value, (int, float)) and math.isfinite(value) and low < value <= high):
        raise ValueError(f'{name} must be in ({low:g}, {high:g}], found {value!r}')


def _positive(name: str, value: float) -> None:
    """Raise unless ``value`` is a finite number > 0."""
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
        raise ValueError(f'{name} must be a finite number > 0, found {value!r}')
