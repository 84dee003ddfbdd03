"""Small rclpy helpers shared by the recorder and the player (message classes, stop signals)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
import importlib
import signal
import threading
from types import FrameType
from typing import Any

from cgail_bags.errors import BagError


def get_message_class(type_name: str) -> Any:
    """The Python message class of ``pkg/msg/Name`` (or ``pkg/Name``).

    Uses ``rosidl_runtime_py.utilities.get_message`` when installed, else imports
    ``pkg.msg`` directly (the PyPI ROS wheels ship the generated packages, not rosidl_runtime_py).

    Raises:
        BagError: Unknown package or message.
    """
    try:
        from rosidl_runtime_py.utilities import get_message  # type: ignore[import-not-found]
    except ImportError:
        get_message = None
    if get_message is not None:
        try:
            return get_message(type_name)
        except (AttributeError, ModuleNotFoundError, ValueError) as exc:
            raise BagError(f'unknown message type {type_name!r} ({exc})') from None
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise BagError(f'expected a message type like pkg/msg/Name, found {type_name!r}')
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f'{pkg}.{kind}')
        return getattr(module, name)
    except (ImportError, AttributeError):
        raise BagError(f'unknown message type {type_name!r}: cannot import {name} from '
                       f'{pkg}.{kind} (is the package installed?)') from None


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """Set the yielded event on SIGINT/SIGTERM (instead of raising) while inside the block.

    The recorder and player install it so a Ctrl-C or ``kill`` always reaches their clean
    shutdown path (closing the bag) rather than unwinding through rclpy.
    """
    stop = threading.Event()

    def handler(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
