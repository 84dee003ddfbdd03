"""Exceptions of the guidance GUI."""


class GuiError(Exception):
    """Base of every GUI error."""


class ProtocolError(GuiError, ValueError):
    """A client message that is not valid JSON or not one of the known commands."""


class ServerError(GuiError, OSError):
    """The HTTP/WebSocket server could not start (address in use, bad bind address...)."""
