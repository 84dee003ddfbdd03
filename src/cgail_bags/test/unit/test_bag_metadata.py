"""Bags written here name their distribution: ``ros_distro: jazzy`` (not rosbags' default)."""

from pathlib import Path
import struct

import pytest
from rosbags.rosbag2 import Reader, StoragePlugin
from rosbags.rosbag2.writer import CompressionFormat, CompressionMode
import yaml

from cgail_bags.bagio import BagWriter, iter_raw, JazzyWriter, open_bag, TYPESTORE
from cgail_bags.qos import LATCHED

T0 = 1_700_000_000 * 10**9


def _string(text: str) -> bytes:
    return TYPESTORE.serialize_cdr(TYPESTORE.types['std_msgs/msg/String'](data=text),
                                   'std_msgs/msg/String')


def _info(bag: Path) -> dict:
    return yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']


def _mcap_metadata(path: Path) -> dict[str, dict[str, str]]:
    """The Metadata records (opcode 0x0C) of an MCAP file: ``{name: {key: value}}``."""
    data = path.read_bytes()
    out: dict[str, dict[str, str]] = {}

    def string(pos: int) -> tuple[str, int]:
        (n,) = struct.unpack_from('<I', data, pos)
        return data[pos + 4:pos + 4 + n].decode(), pos + 4 + n

    pos = 8  # magic
    while pos < len(data) - 8:
        opcode, length = struct.unpack_from('<BQ', data, pos)
        body = pos + 9
        if opcode == 0x0C:
            name, p = string(body)
            (size,) = struct.unpack_from('<I', data, p)
            p, end, entries = p + 4, p + 4 + size, {}
            while p < end:
                key, p = string(p)
                entries[key], p = string(p)
            out[name] = entries
        if opcode == 0x02:  # footer
            break
        pos = body + length
    return out


def test_bag_writer_records_ros_distro_jazzy_and_stays_readable(tmp_path: Path) -> None:
    bag = tmp_path / 'bag'
    with BagWriter(bag, custom_data={'condition': 'cgail', 'ros_distro': 'rosbags'}) as w:
        w.add_topic('/a', 'std_msgs/msg/String', [LATCHED])
        for i in range(3):
            w.write('/a', T0 + i, _string(f'm{i}'))
    info = _info(bag)
    assert info['ros_distro'] == 'jazzy'
    # a custom_data entry of the same name is data, not the field: left as written
    assert info['custom_data'] == {'condition': 'cgail', 'ros_distro': 'rosbags'}
    assert (info['version'], info['storage_identifier'], info['message_count']) == (9, 'mcap', 3)
    # the copy inside the MCAP file (the rosbag2 metadata record) says the same
    record = _mcap_metadata(bag / info['relative_file_paths'][0])['rosbag2']
    assert yaml.safe_load(record['serialized_metadata']) == info
    with open_bag(bag) as reader:
        assert reader.ros_distro == 'jazzy'
        assert [(c.topic, t, TYPESTORE.deserialize_cdr(raw, c.msgtype).data)
                for c, t, raw in iter_raw(reader)] == [('/a', T0 + i, f'm{i}') for i in range(3)]
        assert reader.connections[0].ext.offered_qos_profiles == [LATCHED]
    # the bare .mcap file still opens (its metadata come from the MCAP summary)
    with open_bag(bag / info['relative_file_paths'][0]) as reader:
        assert reader.message_count == 3


@pytest.mark.parametrize('compressed', [False, True])
def test_jazzy_writer_as_rosbags_writer(tmp_path: Path, compressed: bool) -> None:
    """The demonstration bags use the writer directly (zstd chunks): same metadata."""
    if compressed:
        pytest.importorskip('zstandard')
    bag = tmp_path / 'demo'
    writer = JazzyWriter(bag, version=9, storage_plugin=StoragePlugin.MCAP)
    if compressed:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        conn = writer.add_connection('/d', 'std_msgs/msg/String', typestore=TYPESTORE)
        writer.write(conn, T0, _string('x'))
    assert _info(bag)['ros_distro'] == 'jazzy'
    record = _mcap_metadata(next(bag.glob('*.mcap')))['rosbag2']
    assert yaml.safe_load(record['serialized_metadata'])['ros_distro'] == 'jazzy'
    with Reader(bag) as reader:
        assert reader.ros_distro == 'jazzy'
        assert [raw for _, _, raw in reader.messages()] == [_string('x')]
