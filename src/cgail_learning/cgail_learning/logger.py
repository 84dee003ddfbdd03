"""Scalar logging to CSV and to TensorBoard event files (tensorboardX).

:class:`ScalarLogger` writes each scalar to a long-format CSV and, through tensorboardX's
``SummaryWriter``, as a ``simple_value`` scalar to ``events.out.tfevents.<time>.<host>``, which
TensorBoard reads like any ``tf.summary.scalar`` output. :func:`read_event_scalars` reads them
back (tests), checking each record's framing and CRCs and parsing it with tensorboardX's
``Event`` protobuf.
"""

from __future__ import annotations

import csv
from pathlib import Path
import struct

from tensorboardX import SummaryWriter
from tensorboardX.proto.event_pb2 import Event
from tensorboardX.record_writer import masked_crc32c

#: Seconds between flushes of the event file to disk (tensorboardX's default is 120 s).
FLUSH_SECS = 10


def read_event_scalars(path: Path) -> list[tuple[str, float, int]]:
    """``(tag, value, step)`` of every scalar of a TensorBoard event file, in file order.

    Raises:
        ValueError: A record is cut short or fails its CRC.
    """
    out: list[tuple[str, float, int]] = []
    data = path.read_bytes()
    pos = 0
    while pos < len(data):
        if pos + 12 > len(data):
            raise ValueError(f'corrupt record at byte {pos}: cut short')
        header = data[pos:pos + 8]
        (n,) = struct.unpack('<Q', header)
        (header_crc,) = struct.unpack_from('<I', data, pos + 8)
        rec = data[pos + 12:pos + 12 + n]
        if header_crc != masked_crc32c(header) or pos + 16 + n > len(data):
            raise ValueError(f'corrupt record at byte {pos}: bad length')
        (crc,) = struct.unpack_from('<I', data, pos + 12 + n)
        if crc != masked_crc32c(rec):
            raise ValueError(f'corrupt record at byte {pos}: CRC mismatch')
        pos += 16 + n
        event = Event.FromString(rec)
        out.extend((v.tag, v.simple_value, event.step) for v in event.summary.value
                   if v.HasField('simple_value'))
    return out


class ScalarLogger:
    """Flat metric names (``losses/value_loss``) to a long-format CSV and an event file."""

    def __init__(self, log_dir: Path, tensorboard: bool = True,
                 resume_step: int | None = None) -> None:
        """``resume_step``: continue the CSV of a resumed run, dropping its rows past that step
        (logged after the checkpoint the run resumes from); the event file is a new one."""
        log_dir.mkdir(parents=True, exist_ok=True)
        path = log_dir / 'scalars.csv'
        kept: list[list[str]] = []
        if resume_step is not None and path.is_file():
            with path.open(newline='') as f:
                kept = [r for r in list(csv.reader(f))[1:]
                        if len(r) == 3 and r[0].isdigit() and int(r[0]) <= resume_step]
        self._csv_file = path.open('w', newline='')
        self._csv = csv.writer(self._csv_file)
        self._csv.writerow(['step', 'tag', 'value'])
        self._csv.writerows(kept)
        self._tb = (SummaryWriter(str(log_dir), flush_secs=FLUSH_SECS) if tensorboard
                    else None)

    def log(self, step: int, scalars: dict[str, float]) -> None:
        """Write every scalar of ``scalars`` at ``step``."""
        for tag, value in scalars.items():
            self._csv.writerow([step, tag, f'{float(value):.8g}'])
            if self._tb is not None:
                self._tb.add_scalar(tag, float(value), step)
        self._csv_file.flush()

    def close(self) -> None:
        """Close the files."""
        self._csv_file.close()
        if self._tb is not None:
            self._tb.close()
