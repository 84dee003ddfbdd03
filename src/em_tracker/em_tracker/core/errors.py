"""The em_tracker exception tree.

Every error raised by this package derives from :class:`EmTrackerError`, so a node can catch
the whole family at its callback boundary without a bare ``except Exception``.
"""

from __future__ import annotations


class EmTrackerError(Exception):
    """Base class of every error raised by em_tracker."""


class ProtocolError(EmTrackerError, ValueError):
    """A frame on the wire does not follow the NDI Combined API (bad CRC, bad layout...)."""


class DeviceError(EmTrackerError):
    """The Measurement System answered ``ERRORxx`` or ndicapi reported an error code.

    Attributes:
        code: the NDI (``0x01``..``0xF6``) or ndicapi (``0x100``..) error code, or -1 if unknown.
    """

    def __init__(self, message: str, code: int = -1) -> None:
        super().__init__(message)
        self.code = code


class DeviceTimeout(EmTrackerError, TimeoutError):  # noqa: N818
    """The Measurement System did not answer in time."""


class DeviceDisconnected(EmTrackerError, ConnectionError):  # noqa: N818
    """The serial link is gone (port vanished, read/write error, device closed)."""


class CalibrationError(EmTrackerError, ValueError):
    """Fiducials, a traced trajectory or pivoting poses cannot determine the transform asked
    for (too few, non-finite, degenerate geometry, too little rotation)."""


class InputFileError(EmTrackerError, ValueError):
    """A calibration input or output file is missing, unreadable or malformed."""
