"""The one exception tree of pam_controller.

Every error this package raises on purpose derives from :class:`PamError`, so a node can catch
them at the callback boundary without a bare ``except Exception``. Messages read
"expected ..., found ...".
"""

from __future__ import annotations


class PamError(Exception):
    """Base class of every pam_controller error."""


class CommandRejectedError(PamError, ValueError):
    """A bend command (or pressure request) was refused: NaN/inf, out of range, e-stop held."""


class ProtocolError(PamError, ValueError):
    """A CAN frame could not be decoded: unknown layout, wrong length, bad checksum or value."""


class DeviceUnavailableError(PamError, ConnectionError):
    """The CAN bus could not be opened or a send failed (device or interface gone)."""

