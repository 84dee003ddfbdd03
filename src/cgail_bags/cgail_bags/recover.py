"""Recover the messages of an MCAP bag whose recorder was killed before closing it.

    cgail bag recover CRASHED_BAG -o RECOVERED_BAG

``cgail bag record`` closes its bag cleanly on SIGINT/SIGTERM. After a hard kill (SIGKILL, power
loss) the file has the chunks flushed so far (every ``--flush-period``) but no summary, index or
``metadata.yaml``, so readers refuse it. This tool reads the file's records from the start with
the ``mcap`` package's stream reader, keeps the schemas, channels (with their
``offered_qos_profiles``) and messages of every complete chunk (up to its first damaged
record; nothing of a chunk that fails its CRC), stops at the first incomplete record or damaged
framing, and writes them to a new, complete bag.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
import struct
import sys

from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, McapRecord, Message, Schema
from mcap.stream_reader import get_chunk_data_stream, StreamReader
from rosbags.interfaces import Qos
from rosbags.rosbag2.metadata import parse_qos
import zstandard

from cgail_bags.bagio import BagWriter
from cgail_bags.errors import BagError
from cgail_sim.cli_help import tool_parser

MAGIC = b'\x89MCAP0\r\n'
#: What a damaged record raises in the stream reader: a field cut short (struct.error), a bad
#: string or CRC (ValueError: UnicodeDecodeError, CRCValidationError), a chunk that does not
#: decompress (zstandard.ZstdError; lz4's RuntimeError), a length past any sane size
#: (MemoryError, OverflowError).
_DAMAGED = (McapError, struct.error, ValueError, zstandard.ZstdError, RuntimeError, MemoryError,
            OverflowError)


@dataclass(frozen=True)
class Recovered:
    """What :func:`recover_bag` found."""

    messages: int
    """Messages written to the new bag."""
    topics: tuple[str, ...]
    """Topics with at least a channel record."""
    complete: bool
    """Nothing was lost: the source ended at a record boundary and no record was damaged."""


def _find_mcap(path: Path) -> Path:
    if path.is_file():
        return path
    files = sorted(path.glob('*.mcap')) if path.is_dir() else []
    if len(files) != 1:
        raise BagError(f'{path}: expected one .mcap file to recover, found {len(files)}')
    return files[0]


def _chunk_records(chunk: Chunk) -> tuple[list[McapRecord], bool]:
    """The schema, channel and message records of ``chunk`` up to its first damaged one, and
    whether there was none.

    ``mcap.stream_reader.breakup_chunk`` does the same with the same record readers, but gives
    nothing of a chunk with one damaged record: a chunk that fails its CRC (when it has one) or
    does not decompress gives nothing here either; an uncompressed chunk without a CRC (what
    rosbags writes) keeps the records before the damage, as a crashed recorder's last chunk
    needs.
    """
    try:
        stream, end = get_chunk_data_stream(chunk, validate_crc=True)
    except _DAMAGED:
        return [], False
    out: list[McapRecord] = []
    try:
        while stream.count < end:
            opcode, length = stream.read1(), stream.read8()
            start = stream.count
            if length > end - start:
                return out, False
            record: McapRecord | None = None
            if opcode == Opcode.MESSAGE:
                record = Message.read(stream, length)
            elif opcode == Opcode.CHANNEL:
                record = Channel.read(stream)
            elif opcode == Opcode.SCHEMA:
                record = Schema.read(stream)
            if stream.count - start > length:  # (a field ran past the record: damaged)
                return out, False
            stream.read(length - (stream.count - start))
            if record is not None:
                out.append(record)
    except _DAMAGED:
        return out, False
    return out, True


def recover_bag(source: Path | str, output: Path | str) -> Recovered:
    """Copy the messages of ``source``'s complete chunks into a new bag ``output``.

    Raises:
        BagError: Not an MCAP file, nothing recoverable, or the output exists.
    """
    mcap = _find_mcap(Path(source))
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str, list[Qos]]] = {}
    messages: list[tuple[int, int, bytes]] = []
    size = mcap.stat().st_size
    with mcap.open('rb') as f:
        if f.read(8) != MAGIC:
            raise BagError(f'{mcap}: not an MCAP file (expected the MCAP magic at the start)')
        f.seek(0)
        boundary, complete = 8, True  # the end of the last whole record read
        try:
            # chunks whole (emit_chunks), split here; no record is longer than the file
            for record in StreamReader(f, emit_chunks=True, record_size_limit=size).records:
                if not isinstance(record, Chunk):
                    # (the summary's copies of the schemas and channels, indexes, metadata)
                    boundary = f.tell()
                    continue
                records, whole = _chunk_records(record)
                complete = complete and whole
                for rec in records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec.name
                    elif isinstance(rec, Channel) and rec.schema_id in schemas:
                        profiles = rec.metadata.get('offered_qos_profiles')
                        channels[rec.id] = (rec.topic, schemas[rec.schema_id],
                                            parse_qos(profiles) if profiles else [])
                    elif isinstance(rec, Message):
                        messages.append((rec.channel_id, rec.log_time, rec.data))
                boundary = f.tell()
        except EndOfFile:  # cut: at a record boundary (killed between writes) or inside one
            complete = complete and boundary == size
        except _DAMAGED:  # (the framing itself: nothing after it can be trusted)
            complete = False
    if not channels:
        raise BagError(f'{mcap}: nothing to recover (no complete chunk with a channel)')
    with BagWriter(output, custom_data={'recovered_from': str(mcap)}) as writer:
        for topic, msgtype, qos in channels.values():
            writer.add_topic(topic, msgtype, qos)
        for cid, log_time, payload in sorted(messages, key=lambda m: m[1]):
            if cid in channels:
                writer.write(channels[cid][0], log_time, payload)
        count = writer.count
    return Recovered(count, tuple(sorted(t for t, _, _ in channels.values())), complete)


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail bag recover``."""
    parser = tool_parser('bag recover', __doc__, details=True)
    parser.add_argument('bag', type=Path, help='crashed bag directory or .mcap file')
    parser.add_argument('-o', '--output', type=Path, required=True, help='new bag directory')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail bag recover``; exit status 2 on failure."""
    args = build_parser().parse_args(argv)
    try:
        result = recover_bag(args.bag, args.output)
    except BagError as exc:
        print(f'cgail bag recover: error: {exc}', file=sys.stderr)
        return 2
    tail = ('' if result.complete else
            ' (part of the source is cut or damaged: the records there are lost)')
    print(f'cgail bag recover: wrote {result.messages} messages on {len(result.topics)} topics to '
          f'{args.output}{tail}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
