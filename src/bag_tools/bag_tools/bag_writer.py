"""Write and read rosbag2 (Jazzy, metadata version 9) directories with MCAP storage.

Plain Python (no rclpy). A bag is the directory ``<name>/`` holding

- ``metadata.yaml``: the single key ``rosbag2_bagfile_information`` (``version: 9``,
  ``storage_identifier: mcap``, ``ros_distro: jazzy``, per-topic metadata with
  ``offered_qos_profiles`` as a YAML list of maps with string policy values, counts, files);
- ``<name>_0.mcap``, ``<name>_1.mcap``, ... (one more each time ``max_file_size`` is reached).

Each MCAP file is laid out as Jazzy's ``rosbag2_storage_mcap`` plugin writes it: header
profile ``ros2``; one schema per type (name ``pkg/msg/Type``, encoding ``ros2msg``, data the
full definition); one channel per topic (message encoding ``cdr``, metadata
``offered_qos_profiles`` = the profiles as a YAML string and ``topic_type_hash`` = RIHS01);
messages with ``log_time`` = receive time and ``publish_time`` = header/send time; chunks of
768 KiB (the MCAP C++ default rosbag2 keeps), uncompressed (rosbag2's default for MCAP),
with chunk CRCs (which rosbag2 turns off for speed; readers accept both); a
metadata record ``rosbag2`` with key ``serialized_metadata`` written when a file is opened
and again, complete, before it is closed; a summary (schemas, channels, statistics, chunk
and metadata indexes) written on close.

Crash safety: every chunk goes to the operating system as soon as it is finalized (no user
space buffering), so a killed process loses at most the chunk being filled; ``flush()``
finalizes it early. Each write leaves the file ending in a footer without a summary, so a
killed recording's files are valid MCAP that streaming readers read whole; ``reindex``
(bag_tools.reindex) adds the summary and ``metadata.yaml`` that indexed readers and
rosbags need. ``BagReader`` reads such a bag without either.
"""

from __future__ import annotations

import heapq
import os
import re
import struct
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Literal, Self

import yaml
import zstandard
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import Channel, Message, Schema
from mcap.writer import CompressionType, Writer

from bag_tools.message_definitions import definition, type_hash
from vgm_common.errors import VgmError

METADATA_FILENAME = 'metadata.yaml'
METADATA_VERSION = 9  # rosbag2_storage::BagMetadata::version in Jazzy
STORAGE_IDENTIFIER = 'mcap'
ROS_DISTRO = 'jazzy'
MCAP_PROFILE = 'ros2'
DEFAULT_CHUNK_SIZE = 768 * 1024  # [bytes] mcap::DefaultChunkSize, kept by rosbag2's MCAP plugin
MAX_TIME_NS = 2**63 - 1  # rosbag2's starting_time before the first message

# rmw's RMW_DURATION_INFINITE as rosbag2 writes it ({sec, nsec} of INT64_MAX ns).
INFINITE_DURATION = {'sec': 9223372036, 'nsec': 854775807}

MCAP_MAGIC = b'\x89MCAP0\r\n'

try:
    _VERSION = version('bag_tools')
except PackageNotFoundError:  # run from the source tree
    _VERSION = '0.1.0'
try:
    _MCAP_VERSION = version('mcap')
except PackageNotFoundError:
    _MCAP_VERSION = 'unknown'
LIBRARY = f'bag_tools {_VERSION} (mcap-python/{_MCAP_VERSION})'
"""The MCAP header's library string: who wrote the file (honestly not rosbag2)."""

_COMPRESSION = {
    '': CompressionType.NONE,
    'none': CompressionType.NONE,
    'zstd': CompressionType.ZSTD,
    'lz4': CompressionType.LZ4,
}

# rmw_qos_*_policy_to_str spellings; integers are the enum values metadata version <= 8 used.
_POLICY_NAMES = {
    'history': ('system_default', 'keep_last', 'keep_all', 'unknown'),
    'reliability': ('system_default', 'reliable', 'best_effort', 'unknown', 'best_available'),
    'durability': ('system_default', 'transient_local', 'volatile', 'unknown', 'best_available'),
    'liveliness': (
        'system_default',
        'automatic',
        'manual_by_node',
        'manual_by_topic',
        'unknown',
        'best_available',
    ),
}
# One offered QoS profile as metadata version 9 stores it (``qos_profile``): policy names,
# depth, durations {sec, nsec} and a flag; values read from a bag are parsed YAML.
QosProfileDict = dict[str, Any]
_QOS_KEYS = (
    'history',
    'depth',
    'reliability',
    'durability',
    'deadline',
    'lifespan',
    'liveliness',
    'liveliness_lease_duration',
    'avoid_ros_namespace_conventions',
)


class BagError(VgmError):
    """Base of the bag errors; ``path`` is the offending bag or file."""

    def __init__(self, message: str, path: str | os.PathLike[str] | None = None) -> None:
        super().__init__(message, key='path', value=path)
        self.path = path


class BagWriterError(BagError):
    """The bag cannot be created or written (existing directory, unknown topic, closed)."""


class BagReaderError(BagError):
    """The path is not a readable rosbag2 MCAP bag."""


class BagDamagedError(BagReaderError):
    """A data file of the bag is damaged (overwritten bytes, cut short): reading it failed
    after ``messages_read`` messages of that file."""

    def __init__(self, message: str, path: Path, messages_read: int) -> None:
        super().__init__(message, path)
        self.messages_read = messages_read


# What mcap's readers raise on a damaged file: its own errors (EndOfFile, CRC mismatch),
# a length field read as garbage (OverflowError, MemoryError, struct.error), bytes that
# decode as nothing (UnicodeDecodeError is a ValueError) and the decompressors' errors
# (zstandard's ZstdError, lz4's RuntimeError).
_DAMAGE_ERRORS = (
    McapError,
    struct.error,
    EOFError,
    ValueError,
    IndexError,
    KeyError,
    OverflowError,
    MemoryError,
    RuntimeError,
    zstandard.ZstdError,
)


def qos_profile(
    history: str = 'keep_last',
    depth: int = 10,
    reliability: str = 'reliable',
    durability: str = 'volatile',
    deadline: Mapping[str, int] | None = None,
    lifespan: Mapping[str, int] | None = None,
    liveliness: str = 'automatic',
    liveliness_lease_duration: Mapping[str, int] | None = None,
    avoid_ros_namespace_conventions: bool = False,
) -> QosProfileDict:
    """One offered QoS profile as metadata version 9 stores it (a plain dict).

    Policies are rmw's strings (``keep_last``, ``reliable``, ``transient_local``, ``automatic``,
    ``unknown``, ...); durations are ``{'sec': int, 'nsec': int}`` and default to infinite.
    Key order is rosbag2's.
    """
    return {
        'history': history,
        'depth': int(depth),
        'reliability': reliability,
        'durability': durability,
        'deadline': dict(deadline or INFINITE_DURATION),
        'lifespan': dict(lifespan or INFINITE_DURATION),
        'liveliness': liveliness,
        'liveliness_lease_duration': dict(liveliness_lease_duration or INFINITE_DURATION),
        'avoid_ros_namespace_conventions': bool(avoid_ros_namespace_conventions),
    }


def normalize_qos_profiles(profiles: object) -> list[QosProfileDict]:
    """Offered QoS profiles from any metadata version as a list of version 9 dicts.

    Accepts the version 9 list, the version 4-8 YAML string, integer policy values, or None.

    Raises:
        BagReaderError: the profiles are not a list of QoS maps.
    """
    if profiles is None or profiles == '':
        return []
    if isinstance(profiles, str):
        profiles = yaml.safe_load(profiles) or []
    if not isinstance(profiles, list):
        raise BagReaderError(f'offered_qos_profiles is not a list: {profiles!r}')
    result = []
    for profile in profiles:
        if not isinstance(profile, dict):
            raise BagReaderError(f'offered QoS profile is not a map: {profile!r}')
        normalized = qos_profile()
        for key in _QOS_KEYS:
            if key not in profile:
                continue
            value = profile[key]
            names = _POLICY_NAMES.get(key)
            if names is not None and isinstance(value, int) and not isinstance(value, bool):
                value = names[value] if 0 <= value < len(names) else 'unknown'
            normalized[key] = value
        result.append(normalized)
    return result


def header_stamp_ns(data: bytes) -> int | None:
    """``header.stamp`` [ns since epoch] of a CDR message whose first field is a
    ``std_msgs/Header``, or None if it is zero, negative or unreadable.

    Reads 8 bytes instead of deserializing: after the 4-byte encapsulation header (byte 1
    = 1 for little endian CDR, 0 for big endian) come ``stamp.sec`` (int32) and
    ``stamp.nanosec`` (uint32), already aligned.
    """
    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        return None
    sec, nanosec = struct.unpack_from('<iI' if data[1] == 1 else '>iI', data, 4)
    stamp_ns = sec * 1_000_000_000 + nanosec
    return stamp_ns if stamp_ns > 0 else None


class _YamlCppStyleDumper(yaml.SafeDumper):
    """Emit YAML the way yaml-cpp (hence rosbag2) does: sequences indented under their key,
    ``""`` for empty strings, ``~`` for null. Only cosmetic; any YAML parser reads both."""

    def increase_indent(self, flow: bool = False, indentless: bool = False) -> None:
        return super().increase_indent(flow, False)


_YamlCppStyleDumper.add_representer(
    str,
    lambda dumper, data: dumper.represent_scalar(
        'tag:yaml.org,2002:str', data, style='"' if data == '' else None
    ),
)
_YamlCppStyleDumper.add_representer(
    type(None), lambda dumper, _data: dumper.represent_scalar('tag:yaml.org,2002:null', '~')
)


def dump_yaml(data: object) -> str:
    """YAML text of ``data`` in yaml-cpp's block style, keys in insertion order, no final
    newline (``YAML::Dump`` does not write one)."""
    return yaml.dump(
        data,
        Dumper=_YamlCppStyleDumper,
        default_flow_style=False,
        sort_keys=False,
        allow_unicode=True,
        width=float('inf'),
    ).rstrip('\n')


def serialize_qos_profiles(profiles: Sequence[Mapping[str, Any]]) -> str:
    """The ``offered_qos_profiles`` channel metadata string (``serialize_rclcpp_qos_vector``)."""
    return dump_yaml([dict(p) for p in profiles]) if profiles else '[]'


@dataclass
class TopicInfo:
    """A recorded topic: its metadata as in ``topics_with_message_count``."""

    name: str
    type: str
    offered_qos_profiles: list[QosProfileDict] = field(default_factory=list)
    type_description_hash: str = ''
    serialization_format: str = 'cdr'
    message_count: int = 0

    def as_metadata(self) -> dict[str, Any]:
        """The topic's entry of ``topics_with_message_count`` in ``metadata.yaml``."""
        return {
            'topic_metadata': {
                'name': self.name,
                'type': self.type,
                'serialization_format': self.serialization_format,
                'offered_qos_profiles': [dict(p) for p in self.offered_qos_profiles],
                'type_description_hash': self.type_description_hash,
            },
            'message_count': self.message_count,
        }


@dataclass
class _FileInfo:
    path: str
    starting_time: int = MAX_TIME_NS  # [ns since epoch]
    end_time: int = 0  # [ns since epoch]
    message_count: int = 0

    def as_metadata(self) -> dict[str, Any]:
        return {
            'path': self.path,
            'starting_time': {'nanoseconds_since_epoch': self.starting_time},
            'duration': {'nanoseconds': max(0, self.end_time - self.starting_time)},
            'message_count': self.message_count,
        }


# What a killed recording ends with: a DataEnd record (data section CRC 0 = not
# computed), a Footer without a summary (summary start 0) and the closing magic.
_SEAL = struct.pack('<BQI', 0x0F, 4, 0) + struct.pack('<BQQQI', 0x02, 20, 0, 0, 0) + MCAP_MAGIC


class _SealedFile:
    """The write side of an MCAP file that is complete after every write.

    No user-space buffer: what ``write`` returns from is in the operating system (it
    survives the process being killed); mcap's Writer writes whole records (a chunk at a
    time), so this costs nothing. Each write also ends the file with ``_SEAL``, which the
    next write overwrites, so a file cut short by a crash is still a valid MCAP file
    without a summary: streaming readers (mcap's NonSeekingReader in log-time order, or
    its seeking reader, which falls back to streaming) read every chunk written.
    ``close`` cuts the last seal off behind the Writer's own footer."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self._position = 0

    def write(self, data: bytes) -> int:
        # One call: the seal moves with the data, the file is never left without one
        # (unless the kernel cuts the write itself short).
        view = memoryview(bytes(data) + _SEAL)
        offset = self._position
        while view:
            written = os.pwrite(self._fd, view, offset)
            view = view[written:]
            offset += written
        self._position += len(data)
        return len(data)

    def tell(self) -> int:
        return self._position

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._fd >= 0:
            os.ftruncate(self._fd, self._position)
            os.close(self._fd)
            self._fd = -1


class BagWriter:
    """Writes one rosbag2 directory. Not thread-safe: call from one thread.

    Args:
        path: the bag directory ``.../<name>``; must not exist (rosbag2 never overwrites).
        max_file_size: split to ``<name>_<n+1>.mcap`` once a file reaches this size [bytes];
            0 = never split.
        chunk_size: uncompressed chunk size that triggers writing a chunk [bytes].
        compression: chunk compression, ``''`` (rosbag2's default), ``'zstd'`` or ``'lz4'``.
        custom_data: ``custom_data`` of the metadata (str -> str), or None.

    Raises:
        BagWriterError: the directory exists or cannot be created.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        max_file_size: int = 0,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: str = '',
        custom_data: Mapping[str, str] | None = None,
    ) -> None:
        self.path = Path(path)
        if compression not in _COMPRESSION:
            raise BagWriterError(f'unknown compression {compression!r}', self.path)
        if max_file_size < 0 or chunk_size <= 0:
            raise BagWriterError('max_file_size must be >= 0 and chunk_size > 0', self.path)
        try:
            self.path.mkdir(parents=True, exist_ok=False)
        except FileExistsError:
            raise BagWriterError(
                f'bag directory {self.path} already exists; not overwriting', self.path
            ) from None
        except OSError as error:
            raise BagWriterError(
                f'cannot create {self.path}: {error.strerror}', self.path
            ) from None
        self.max_file_size = int(max_file_size)
        self._chunk_size = int(chunk_size)
        self._compression = _COMPRESSION[compression]
        self._custom_data = dict(custom_data) if custom_data else None
        self._topics: dict[str, TopicInfo] = {}  # name -> TopicInfo, in creation order
        self._files: list[_FileInfo] = []  # _FileInfo per file, the last one open
        self._channel_ids: dict[str, int] = {}  # topic name -> channel id in the open file
        self._schema_ids: dict[str, int] = {}  # type -> schema id in the open file
        self._stream: _SealedFile  # the open file's, set by _open_file
        self._writer: Writer
        self._closed = False
        self._open_file()

    # -- public API ----------------------------------------------------------------------

    @property
    def topics(self) -> list[TopicInfo]:
        """Copies of the topics added so far, with their message counts."""
        return [TopicInfo(**vars(t)) for t in self._topics.values()]

    @property
    def message_count(self) -> int:
        """The number of messages written so far, all topics together."""
        return sum(t.message_count for t in self._topics.values())

    def topic_type(self, name: str) -> str | None:
        """The type ``name`` is recorded with, or None."""
        topic = self._topics.get(name)
        return None if topic is None else topic.type

    @property
    def file_paths(self) -> list[Path]:
        """Paths of the data files written so far (the last one may still be open)."""
        return [self.path / f.path for f in self._files]

    @property
    def closed(self) -> bool:
        """True once ``close`` was called."""
        return self._closed

    def add_topic(
        self,
        name: str,
        type_name: str,
        offered_qos_profiles: Iterable[Mapping[str, Any]] = (),
        type_description_hash: str | None = None,
    ) -> None:
        """Create the topic's schema and channel. Adding an existing topic is a no-op.

        Args:
            name: topic name, e.g. ``/stereo/left/image_raw``.
            type_name: ``pkg/msg/Type``.
            offered_qos_profiles: the publishers' profiles, dicts as made by ``qos_profile``.
            type_description_hash: RIHS01 string; default: the installed type's hash.

        Raises:
            BagWriterError: closed, or a different type for an existing topic.
            DefinitionNotFoundError: the type's definition is not installed.
        """
        self._check_open()
        existing = self._topics.get(name)
        if existing is not None:
            if existing.type != type_name:
                raise BagWriterError(
                    f'topic {name} already recorded with type {existing.type}, not {type_name}',
                    self.path,
                )
            return
        if type_description_hash is None:
            type_description_hash = type_hash(type_name)
        definition(type_name)  # fail here, not half-way through writing the channel
        topic = TopicInfo(
            name=name,
            type=type_name,
            offered_qos_profiles=normalize_qos_profiles(list(offered_qos_profiles)),
            type_description_hash=type_description_hash,
        )
        self._topics[name] = topic
        self._register(topic)

    def write(
        self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None:
        """Append one serialized (CDR) message.

        Args:
            topic: a name passed to ``add_topic`` before.
            data: the serialized message bytes, CDR encapsulation header included.
            log_time_ns: receive time [ns since epoch].
            publish_time_ns: header/send time [ns since epoch]; default ``log_time_ns``.

        Raises:
            BagWriterError: closed, unknown topic, or negative time.
        """
        self._check_open()
        info = self._topics.get(topic)
        if info is None:
            raise BagWriterError(f'write to {topic} before add_topic', self.path)
        log_time_ns = int(log_time_ns)
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        if log_time_ns < 0 or publish_time_ns < 0:
            raise BagWriterError(f'negative timestamp on {topic}', self.path)
        current = self._files[-1]
        if (
            self.max_file_size
            and current.message_count
            and self._stream.tell() >= self.max_file_size
        ):
            self._split()
            current = self._files[-1]
        self._writer.add_message(
            channel_id=self._channel_ids[topic],
            log_time=log_time_ns,
            data=bytes(data),
            publish_time=publish_time_ns,
            sequence=0,
        )
        info.message_count += 1
        current.message_count += 1
        current.starting_time = min(current.starting_time, log_time_ns)
        current.end_time = max(current.end_time, log_time_ns)

    def flush(self) -> None:
        """Write the chunk being filled now (if it holds messages), so a crash cannot lose it."""
        if not self._closed:
            self._writer.flush()

    def metadata(self) -> dict[str, Any]:
        """The ``rosbag2_bagfile_information`` mapping as it stands now."""
        counted = [f for f in self._files if f.message_count]
        start = min((f.starting_time for f in counted), default=MAX_TIME_NS)
        end = max((f.end_time for f in counted), default=0)
        return {
            'version': METADATA_VERSION,
            'storage_identifier': STORAGE_IDENTIFIER,
            'duration': {'nanoseconds': max(0, end - start)},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': self.message_count,
            'topics_with_message_count': [t.as_metadata() for t in self._topics.values()],
            'compression_format': '',  # chunk compression is invisible to rosbag2 (as rosbag2)
            'compression_mode': '',
            'relative_file_paths': [f.path for f in self._files],
            'files': [f.as_metadata() for f in self._files],
            'custom_data': dict(self._custom_data) if self._custom_data else None,
            'ros_distro': ROS_DISTRO,
        }

    def close(self) -> None:
        """Finish the open file (metadata record, summary, footer) and write
        ``metadata.yaml``. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._finish_file()
        text = dump_yaml({'rosbag2_bagfile_information': self.metadata()}) + '\n'
        temporary = self.path / (METADATA_FILENAME + '.tmp')
        temporary.write_text(text, encoding='utf-8')
        temporary.replace(self.path / METADATA_FILENAME)

    def split(self) -> None:
        """Finish the open file and go on in ``<name>_<n+1>.mcap``."""
        self._check_open()
        self._split()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> Literal[False]:
        self.close()
        return False

    # -- internals ------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise BagWriterError(f'bag {self.path} is closed', self.path)

    def _open_file(self) -> None:
        name = f'{self.path.name}_{len(self._files)}.mcap'
        self._files.append(_FileInfo(path=name))
        self._stream = _SealedFile(self.path / name)
        # mcap's Writer calls only write() and tell() of a stream it did not open; its
        # annotation asks for a whole IO.
        self._writer = Writer(
            self._stream,  # type: ignore[arg-type]
            chunk_size=self._chunk_size,
            compression=self._compression,
        )
        self._writer.start(profile=MCAP_PROFILE, library=LIBRARY)
        self._channel_ids.clear()
        self._schema_ids.clear()
        # rosbag2 writes the metadata once on open and again on close: a file cut short by a
        # crash still says which version and distro wrote it.
        self._write_metadata_record()
        for topic in self._topics.values():
            self._register(topic)

    def _register(self, topic: TopicInfo) -> None:
        schema_id = self._schema_ids.get(topic.type)
        if schema_id is None:
            encoding, text = definition(topic.type)
            schema_id = self._writer.register_schema(
                name=topic.type, encoding=encoding, data=text.encode('utf-8')
            )
            self._schema_ids[topic.type] = schema_id
        self._channel_ids[topic.name] = self._writer.register_channel(
            topic=topic.name,
            message_encoding=topic.serialization_format,
            schema_id=schema_id,
            metadata={
                'offered_qos_profiles': serialize_qos_profiles(topic.offered_qos_profiles),
                'topic_type_hash': topic.type_description_hash,
            },
        )

    def _write_metadata_record(self) -> None:
        self._writer.add_metadata('rosbag2', {'serialized_metadata': dump_yaml(self.metadata())})

    def _finish_file(self) -> None:
        self._writer.flush()  # the last chunk goes before the final metadata record
        self._write_metadata_record()
        self._writer.finish()
        self._stream.close()

    def _split(self) -> None:
        self._finish_file()
        self._open_file()


# -------------------------------------------------------------------------------------------
# Reading


@dataclass(frozen=True)
class BagMessage:
    """One recorded message: ``data`` is the serialized CDR, times are [ns since epoch]."""

    topic: str
    type: str
    data: bytes
    log_time: int
    publish_time: int

    @classmethod
    def of(cls, schema: Schema | None, channel: Channel, message: Message) -> BagMessage:
        """The ``BagMessage`` of an MCAP reader's (schema, channel, message) record."""
        return cls(
            channel.topic,
            schema.name if schema else '',
            message.data,
            message.log_time,
            message.publish_time,
        )


_FILE_INDEX_RE = re.compile(r'_(\d+)\.mcap$')


def _has_footer(path: Path) -> bool:
    """True if the file ends in the MCAP magic, i.e. it was closed (summary written)."""
    size = path.stat().st_size
    if size < 2 * len(MCAP_MAGIC):
        return False
    with open(path, 'rb') as stream:
        stream.seek(-len(MCAP_MAGIC), os.SEEK_END)
        return stream.read(len(MCAP_MAGIC)) == MCAP_MAGIC


def _stream_records_tolerant(
    path: Path, topics: Iterable[str] | None
) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """(schema, channel, message) of a file read front to back, stopping quietly where a
    crash cut it short."""
    with open(path, 'rb') as stream:
        reader = NonSeekingReader(stream)
        iterator = reader.iter_messages(topics=topics, log_time_order=False)
        while True:
            try:
                item = next(iterator)
            except StopIteration:
                return
            except (McapError, struct.error, EOFError, ValueError, IndexError):
                return  # the truncated tail: everything before it was yielded
            yield item


class BagReader:
    """Reads a rosbag2 MCAP directory (as written by ``BagWriter`` or rosbag2).

    A directory without ``metadata.yaml`` (a recording that was killed) is read from its
    ``*.mcap`` files alone: topics and counts are then rebuilt from the channels, and files
    without a summary are read up to their last complete chunk (``recovered`` is True).

    Raises:
        BagReaderError: not a directory, unreadable/invalid metadata, unsupported storage or
            version, or missing data files.
        BagDamagedError: (while iterating ``messages``) a data file is damaged: bytes
            overwritten (chunk CRCs are checked), or cut short (a file of a bag with
            metadata has lost its summary, or lost data since it was opened).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.files: list[Path]  # the data files, in order
        self.metadata: dict[str, Any] | None  # rosbag2_bagfile_information; None if recovered
        self.topics: list[TopicInfo]
        if not self.path.is_dir():
            raise BagReaderError(f'bag directory {self.path} does not exist', self.path)
        metadata_path = self.path / METADATA_FILENAME
        self.recovered = not metadata_path.exists()
        if self.recovered:
            self._recover_metadata()
        else:
            self._read_metadata(metadata_path)

    def _read_metadata(self, metadata_path: Path) -> None:
        try:
            document = yaml.safe_load(metadata_path.read_text(encoding='utf-8'))
            info = document['rosbag2_bagfile_information']
            bag_version = int(info['version'])
            storage = info['storage_identifier']
            relative_paths = list(info['relative_file_paths'])
            topics = [
                TopicInfo(
                    name=t['topic_metadata']['name'],
                    type=t['topic_metadata']['type'],
                    serialization_format=t['topic_metadata'].get('serialization_format', 'cdr'),
                    offered_qos_profiles=normalize_qos_profiles(
                        t['topic_metadata'].get('offered_qos_profiles')
                    ),
                    type_description_hash=t['topic_metadata'].get('type_description_hash', ''),
                    message_count=int(t.get('message_count', 0)),
                )
                for t in info.get('topics_with_message_count') or []
            ]
        except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as error:
            raise BagReaderError(
                f'{metadata_path} is not rosbag2 metadata ({type(error).__name__}: {error})',
                self.path,
            ) from None
        if bag_version > METADATA_VERSION:
            raise BagReaderError(
                f'rosbag2 metadata version {bag_version} is newer than {METADATA_VERSION}',
                self.path,
            )
        if storage != STORAGE_IDENTIFIER:
            raise BagReaderError(f'storage {storage!r} is not supported (only mcap)', self.path)
        if info.get('compression_mode'):
            raise BagReaderError(
                f'compression mode {info["compression_mode"]!r} is not supported', self.path
            )
        self.files = [self.path / Path(p).name for p in relative_paths]
        missing = [str(p) for p in self.files if not p.is_file()]
        if missing:
            raise BagReaderError(f'bag {self.path} misses data files {missing}', self.path)
        self.metadata = info
        self.topics = topics

    def _recover_metadata(self) -> None:
        indices = {
            p: int(match.group(1))
            for p in self.path.glob('*.mcap')
            if (match := _FILE_INDEX_RE.search(p.name))
        }  # file -> its n
        if not indices:
            raise BagReaderError(
                f'{self.path} is not a bag: no {METADATA_FILENAME} and no <name>_<n>.mcap files',
                self.path,
            )
        self.files = sorted(indices, key=indices.__getitem__)
        topics: dict[str, TopicInfo] = {}
        for path in self.files:
            for schema, channel, _message in _stream_records_tolerant(path, None):
                topic = topics.get(channel.topic)
                if topic is None:
                    topic = topics[channel.topic] = TopicInfo(
                        name=channel.topic,
                        type=schema.name if schema else '',
                        serialization_format=channel.message_encoding,
                        offered_qos_profiles=normalize_qos_profiles(
                            channel.metadata.get('offered_qos_profiles')
                        ),
                        type_description_hash=channel.metadata.get('topic_type_hash', ''),
                    )
                topic.message_count += 1
        self.topics = list(topics.values())
        self.metadata = None

    @property
    def message_count(self) -> int:
        """The number of messages in the bag, all topics together."""
        return sum(t.message_count for t in self.topics)

    def topic(self, name: str) -> TopicInfo | None:
        """The ``TopicInfo`` of ``name``, or None."""
        return next((t for t in self.topics if t.name == name), None)

    def file_messages(
        self, path: Path, topics: Iterable[str] | None = None, cut_short_ok: bool = False
    ) -> Iterator[BagMessage]:
        """Iterate ``BagMessage`` of one of ``files`` in log-time order (``topics``: names
        to keep; None = all). A file without a summary is read up to its last complete
        chunk if the bag is ``recovered`` or ``cut_short_ok`` (reindex), else refused."""
        if _has_footer(path):
            read = 0
            try:
                with open(path, 'rb') as stream:
                    # CRCs checked: overwritten message bytes are otherwise played as valid.
                    reader = SeekingReader(stream, validate_crcs=True)
                    for record in reader.iter_messages(topics=topics, log_time_order=True):
                        yield BagMessage.of(*record)
                        read += 1
            except _DAMAGE_ERRORS as error:
                raise BagDamagedError(
                    f'{path} is damaged after {read} messages ({type(error).__name__}: {error})',
                    path,
                    read,
                ) from None
            return
        if not (self.recovered or cut_short_ok):
            # metadata.yaml is written once every file is closed (summary and footer):
            # a file without them was cut short since.
            raise BagDamagedError(
                f'{path} is damaged: cut short (no summary; reindex keeps what is left)',
                path,
                0,
            )
        unindexed = _stream_records_tolerant(path, topics)
        yield from (BagMessage.of(*r) for r in sorted(unindexed, key=lambda r: r[2].log_time))

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Iterate ``BagMessage`` in log-time order over all files.

        Args:
            topics: iterable of topic names to keep; None = all.
        """
        topics = None if topics is None else sorted(set(topics))
        iterators = [self.file_messages(path, topics) for path in self.files]
        return heapq.merge(*iterators, key=lambda m: m.log_time)
