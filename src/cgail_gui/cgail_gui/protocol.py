"""Messages between ``gui_node`` and the page (JSON text frames over the WebSocket).

Node -> page: one kind of message::

    {"type": "state", "full": true|false, "source": "live"|"replay", "epoch": int,
     "items": {name: item, ...}}

``full`` states carry every item (sent on connect, on ``resync`` and whenever the source
switches: ``epoch`` counts the switches); other states carry the items changed since the last
one sent to that page, newest values only. Items are those of
:data:`cgail_gui.state.ITEMS`; positions are in metres in frame ``phantom``, angles in
rad (the page shows mm and degrees); arrays of the mesh are base64 little-endian float32 /
uint32.

Page -> node (anything else is ignored with a log line)::

    {"type": "ack"}       (after handling each state: the node sends the next one only then,
                           or after 1 s, so a page that draws slowly gets merged, fresh states
                           instead of a queue)
    {"type": "resync"}
    {"type": "trial", "action": "start"|"stop"|"reset"}
    {"type": "replay", "action": "start", "bag": "<name from the replay item>",
     "rate": 0.1..10 (default 1), "loop": bool (default false)}
    {"type": "replay", "action": "stop"}
    {"type": "joy", "axes": [float in [-1, 1], ...], "buttons": [0|1, ...]}
                          (the page's keyboard as a gamepad, ``record_demos``: at most
                           MAX_JOY_AXES axes and MAX_JOY_BUTTONS buttons)
    {"type": "record", "action": "discard"}   (``record_demos``: drop the episode)
"""

from __future__ import annotations

from dataclasses import dataclass
import json
import math
from typing import Any

from cgail_gui.errors import ProtocolError

MAX_CLIENT_MESSAGE = 4096
"""Largest client message accepted, bytes (the server drops bigger frames)."""
MAX_JOY_AXES = 16
"""Most axes a page's ``joy`` message may carry."""
MAX_JOY_BUTTONS = 32
"""Most buttons a page's ``joy`` message may carry."""


@dataclass(frozen=True)
class ClientCommand:
    """A validated page command."""

    kind: str
    """``ack``, ``resync``, ``trial``, ``replay``, ``joy`` or ``record``."""
    action: str = ''
    """``start``/``stop``/``reset`` (trial), ``start``/``stop`` (replay), ``discard``
    (record); '' for resync and joy."""
    bag: str = ''
    """Bag name for ``replay start``."""
    rate: float = 1.0
    """Playback rate for ``replay start``."""
    loop: bool = False
    """Loop the bag for ``replay start``."""
    axes: tuple[float, ...] = ()
    """``joy``: the axes, each finite in [-1, 1]."""
    buttons: tuple[int, ...] = ()
    """``joy``: the buttons, each 0 or 1."""


def encode_state(items: dict[str, Any], *, full: bool, source: str, epoch: int) -> str:
    """The text of one ``state`` message."""
    return json.dumps({'type': 'state', 'full': full, 'source': source, 'epoch': epoch,
                       'items': items}, separators=(',', ':'), allow_nan=False)


def parse_client_message(data: str | bytes) -> ClientCommand:
    """Validate one message from the page.

    Raises:
        ProtocolError: binary, too long, not JSON, not an object, or not a known command;
            the message says what was expected.
    """
    if isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError('expected a JSON text frame, found a binary frame')
    if len(data) > MAX_CLIENT_MESSAGE:
        raise ProtocolError(f'expected at most {MAX_CLIENT_MESSAGE} characters, '
                            f'found {len(data)}')
    try:
        msg = json.loads(data)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ProtocolError(f'expected JSON, found {data[:40]!r} ({exc})') from None
    if not isinstance(msg, dict):
        raise ProtocolError(f'expected a JSON object, found {type(msg).__name__}')
    kind = msg.get('type')
    if kind in ('resync', 'ack'):
        return ClientCommand(kind)
    action = msg.get('action')
    if kind == 'trial':
        if action not in ('start', 'stop', 'reset'):
            raise ProtocolError(f"expected trial action start, stop or reset, found {action!r}")
        return ClientCommand('trial', action)
    if kind == 'replay':
        if action == 'stop':
            return ClientCommand('replay', 'stop')
        if action != 'start':
            raise ProtocolError(f"expected replay action start or stop, found {action!r}")
        bag = msg.get('bag')
        if not isinstance(bag, str) or not bag or len(bag) > 300:
            raise ProtocolError(f'expected replay bag to be a bag name, found {bag!r}')
        rate = msg.get('rate', 1.0)
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) \
                or not math.isfinite(rate) or not 0.1 <= rate <= 10.0:
            raise ProtocolError(f'expected replay rate in [0.1, 10], found {rate!r}')
        loop = msg.get('loop', False)
        if not isinstance(loop, bool):
            raise ProtocolError(f'expected replay loop true or false, found {loop!r}')
        return ClientCommand('replay', 'start', bag=bag, rate=float(rate), loop=loop)
    if kind == 'joy':
        return _joy_command(msg)
    if kind == 'record':
        if action != 'discard':
            raise ProtocolError(f'expected record action discard, found {action!r}')
        return ClientCommand('record', 'discard')
    raise ProtocolError(f'expected type ack, resync, trial, replay, joy or record, found '
                        f'{kind!r}')


def _joy_command(msg: dict[str, Any]) -> ClientCommand:
    """A page ``joy`` message: axes finite in [-1, 1], buttons 0 or 1 (JSON's NaN included:
    Python's parser accepts it)."""
    axes, buttons = msg.get('axes'), msg.get('buttons')
    if not isinstance(axes, list) or len(axes) > MAX_JOY_AXES or not all(
            isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a)
            and -1.0 <= a <= 1.0 for a in axes):
        raise ProtocolError(f'expected joy axes: at most {MAX_JOY_AXES} finite numbers in '
                            f'[-1, 1], found {str(axes)[:80]}')
    if not isinstance(buttons, list) or len(buttons) > MAX_JOY_BUTTONS or not all(
            b in (0, 1) and not isinstance(b, float) for b in buttons):
        raise ProtocolError(f'expected joy buttons: at most {MAX_JOY_BUTTONS} values 0 or 1, '
                            f'found {str(buttons)[:80]}')
    return ClientCommand('joy', axes=tuple(float(a) for a in axes),
                         buttons=tuple(int(b) for b in buttons))
