"""Gamepad access behind a small Protocol: SDL2 through pygame, and a scripted fake.

``SDL_VIDEODRIVER=dummy`` (set by ``scripts/env.sh``) lets SDL run headless; pygame needs its
(dummy) video subsystem for the event pump that refreshes joystick state and reports hot-plug.
"""

from __future__ import annotations

from collections.abc import Iterable
import os
from typing import Any, Protocol

from catheter_driver.core.joy_filter import JoySample
from catheter_driver.exceptions import DeviceDisconnectedError, GamepadNotFoundError


class Gamepad(Protocol):
    """An open gamepad."""

    name: str

    def read(self) -> JoySample:
        """Return the current state.

        Raises:
            DeviceDisconnectedError: if the device was unplugged.
        """

    def close(self) -> None:
        """Release the device."""


class GamepadFactory(Protocol):
    """Opens a gamepad by index or name (name wins when not empty, as in ROS joy)."""

    def __call__(self, device_id: int, device_name: str) -> Gamepad:
        """Open it or raise :class:`GamepadNotFoundError`."""


def _pygame() -> Any:
    os.environ.setdefault('SDL_VIDEODRIVER', 'dummy')
    os.environ.setdefault('PYGAME_HIDE_SUPPORT_PROMPT', '1')
    import pygame

    if not pygame.display.get_init():
        pygame.display.init()
    if not pygame.joystick.get_init():
        pygame.joystick.init()
    return pygame


class SdlGamepad:
    """A gamepad read through pygame's SDL2 joystick API."""

    def __init__(self, joystick: Any, pygame: Any) -> None:
        """Wrap an opened ``pygame.joystick.Joystick``; use :meth:`open`."""
        self._js = joystick
        self._pg = pygame
        self._instance_id = joystick.get_instance_id()
        self.name: str = joystick.get_name()

    @classmethod
    def open(cls, device_id: int, device_name: str) -> SdlGamepad:
        """Open a gamepad (the :class:`GamepadFactory` of the real node).

        Raises:
            GamepadNotFoundError: no device with that index/name is present.
        """
        pg = _pygame()
        pg.event.pump()
        count = pg.joystick.get_count()
        names = [pg.joystick.Joystick(i).get_name() for i in range(count)]
        if device_name:
            if device_name not in names:
                raise GamepadNotFoundError(
                    f'expected a gamepad named {device_name!r}, found {names or "none"}')
            device_id = names.index(device_name)
        elif not 0 <= device_id < count:
            raise GamepadNotFoundError(
                f'expected a gamepad with device_id {device_id}, found {count} device(s)'
                f'{": " + ", ".join(names) if names else ""}')
        js = pg.joystick.Joystick(device_id)
        js.init()
        return cls(js, pg)

    def read(self) -> JoySample:
        """Pump SDL events and read axes, buttons and hats."""
        pg = self._pg
        for event in pg.event.get():
            if (event.type == pg.JOYDEVICEREMOVED
                    and getattr(event, 'instance_id', None) == self._instance_id):
                raise DeviceDisconnectedError(f'gamepad {self.name!r} was unplugged')
        js = self._js
        axes = tuple(max(-32768, min(32767, round(js.get_axis(i) * 32768.0)))
                     for i in range(js.get_numaxes()))
        buttons = tuple(bool(js.get_button(i)) for i in range(js.get_numbuttons()))
        hats = tuple(tuple(js.get_hat(i)) for i in range(js.get_numhats()))
        return JoySample(axes, buttons, hats)  # type: ignore[arg-type]

    def close(self) -> None:
        """Close the joystick (SDL stays initialised for the next open)."""
        self._js.quit()


class FakeGamepad:
    """A scripted gamepad for tests and demos (the SDL device's simulated twin)."""

    def __init__(self, n_axes: int = 6, n_buttons: int = 12, n_hats: int = 1,
                 name: str = 'Fake Gamepad') -> None:
        """Create it centred with no button pressed."""
        self.name = name
        self.axes = [0] * n_axes
        self.buttons = [False] * n_buttons
        self.hats = [(0, 0)] * n_hats
        self.plugged = True
        self.closed = False

    def set(self, axes: Iterable[int] | None = None, buttons: Iterable[bool] | None = None,
            hats: Iterable[tuple[int, int]] | None = None) -> None:
        """Change the state seen by the next :meth:`read`."""
        if axes is not None:
            self.axes = list(axes)
        if buttons is not None:
            self.buttons = list(buttons)
        if hats is not None:
            self.hats = list(hats)

    def read(self) -> JoySample:
        """Current scripted state, or DeviceDisconnectedError after :attr:`plugged` is False."""
        if not self.plugged:
            raise DeviceDisconnectedError(f'gamepad {self.name!r} was unplugged')
        return JoySample(tuple(self.axes), tuple(self.buttons), tuple(self.hats))

    def close(self) -> None:
        """Mark closed."""
        self.closed = True


class FakeGamepadFactory:
    """A :class:`GamepadFactory` that hands out one :class:`FakeGamepad` when it is plugged."""

    def __init__(self, gamepad: FakeGamepad | None = None) -> None:
        """``gamepad=None`` means no device is present (yet)."""
        self.gamepad = gamepad
        self.attempts = 0

    def __call__(self, device_id: int, device_name: str) -> Gamepad:
        """Return the fake gamepad if present and matching."""
        self.attempts += 1
        pad = self.gamepad
        if pad is None or not pad.plugged or device_id != 0 or (
                device_name and device_name != pad.name):
            raise GamepadNotFoundError(
                f'expected a gamepad with device_id {device_id}'
                f'{f" named {device_name!r}" if device_name else ""}, found none')
        return pad
