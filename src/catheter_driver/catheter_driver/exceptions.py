"""The one exception tree of catheter_driver.

Every error this package raises on purpose derives from :class:`CatheterDriverError`, and also
from the closest builtin so callers that only know the builtins still catch it. Messages read
"expected ..., found ...".
"""

from __future__ import annotations


class CatheterDriverError(Exception):
    """Base class of every catheter_driver error."""


class CommandError(CatheterDriverError, ValueError):
    """A command (insertion velocity, bend) was NaN/inf, out of range or malformed."""


class ProtocolError(CatheterDriverError, ValueError):
    """A device frame could not be decoded or carried implausible values."""


class DeviceDisconnectedError(CatheterDriverError, ConnectionError):
    """The device (CAN bus or gamepad) could not be opened or went away."""


class DeviceTimeoutError(CatheterDriverError, TimeoutError):
    """The device stopped answering within the expected time."""


class GamepadNotFoundError(DeviceDisconnectedError):
    """No gamepad matching ``device_id`` / ``device_name`` is plugged in."""
