"""The recorder's state without ROS: the settings that are the one source of its bag
parameters, the bag it creates, the times each message is stored with, the topics it
records (and those that gained a second type), when the backlog is drained after a stop
request, and what its diagnostics and closing log say."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bag_tools.bag_writer import BagError, BagWriter, header_stamp_ns
from bag_tools.recording import BagRecording
from vgm_common.errors import VgmError
from vgm_common.settings import setting

# After a stop request, keep taking the messages the middleware already holds until none
# came for QUIET_PERIOD (a recorder behind the publishers must not lose its backlog), at
# most MAX_DRAIN_PERIOD.
QUIET_PERIOD = 0.25  # [s]
MAX_DRAIN_PERIOD = 10.0  # [s]
_COMPRESSION_ALIASES = {'none': ''}  # rosbag2's spelling -> BagWriter's


class RecorderStartupError(VgmError):
    """The output location is unusable; the message says which and why."""


def default_bag_name(now: float | None = None) -> str:
    """``rosbag2_YYYY_MM_DD-HH_MM_SS`` in local time, the name ``ros2 bag record`` picks."""
    return time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S', time.localtime(now))


def _plain_directory_name(name: str) -> str | None:
    """A reason if ``name`` is not usable as one directory name, else None."""
    if '/' in name or name in ('.', '..'):
        return f'must be a plain directory name, got {name!r}'
    return None


@dataclass(frozen=True)
class BagSettings:
    """Where and how the recorder writes its bag: the one source of these parameters."""

    bag_name: str = setting(
        '',
        'Bag directory name; empty = rosbag2_YYYY_MM_DD-HH_MM_SS (local time). Must not '
        'exist yet.',
        check=_plain_directory_name,
        read_only=True,
    )
    output_dir: str = setting(
        'bags',
        'Directory the bag directory is created in (relative to the working directory).',
        read_only=True,
    )
    flush_period: float = setting(
        1.0,
        'The chunk being filled is written at least this often (bounds what a crash '
        'loses); 0 = only when full (768 KiB).',
        unit='s',
        range=(0.0, 3600.0),
        read_only=True,
    )
    max_file_size: int = setting(
        0,
        'Split to <bag_name>_<n+1>.mcap once a file reaches this size; 0 = never.',
        unit='bytes',
        range=(0, 2**62),
        read_only=True,
    )
    compression: str = setting(
        'none',
        'Chunk compression of the MCAP files: none (rosbag2\'s default; "" says the same), '
        "zstd or lz4 (mcap's chunk compression: every MCAP reader decompresses it).",
        choices=('none', '', 'zstd', 'lz4'),
        read_only=True,
    )
    max_cache_size: int = setting(
        100 * 1024 * 1024,
        'Messages waiting to be written; beyond this the oldest are dropped (counted). '
        '0 = unbounded.',
        unit='bytes',
        range=(0, 2**62),
        read_only=True,
    )


class Recorder:
    """A bag being recorded: ``settings`` say where (``bag_path``) and how; ``clock``
    (monotonic [s]) times the drain after a stop request; ``log_clock_ns`` (the node's
    clock [ns]) times a message the middleware did not; ``on_failure(error)`` is called
    from the writer thread once writing failed.

    Raises:
        RecorderStartupError: the bag cannot be created (it exists, no permission...).
    """

    def __init__(
        self,
        settings: BagSettings,
        on_failure: Callable[[Exception], None],
        log_clock_ns: Callable[[], int] = time.time_ns,
        clock: Callable[[], float] = time.monotonic,
        now: float | None = None,  # [s since epoch] names the default bag
    ) -> None:
        self.bag_path = os.path.join(
            settings.output_dir or '.', settings.bag_name or default_bag_name(now)
        )
        try:
            bag = BagWriter(
                self.bag_path,
                max_file_size=settings.max_file_size,
                compression=_COMPRESSION_ALIASES.get(settings.compression, settings.compression),
            )
        except BagError as error:
            raise RecorderStartupError(str(error)) from None
        self.recording = BagRecording(
            bag, settings.max_cache_size, settings.flush_period, on_failure
        )
        self._clock = clock
        self._log_clock_ns = log_clock_ns
        self._stamped: dict[str, bool] = {}  # recorded topic -> its first field is a Header
        self._mixed_types: set[str] = set()  # recorded topics that gained another type
        self._last_message_time = clock()  # [s]

    @property
    def topics(self) -> set[str]:
        """The topics being recorded."""
        return set(self._stamped)

    def add_topic(
        self, name: str, type_name: str, offered_qos: list[dict[str, Any]], stamped: bool
    ) -> None:
        """Record ``name`` from now on; ``stamped``: its first field is a std_msgs/Header
        (its stamp is then the publish time)."""
        self.recording.add_topic(name, type_name, offered_qos)
        self._stamped[name] = stamped

    def new_second_type(self, name: str, types: list[str]) -> str | None:
        """Why ``name``'s messages of other types than its first are not recorded, the
        first time it has several ``types``; else None."""
        if len(types) <= 1 or name in self._mixed_types:
            return None
        self._mixed_types.add(name)
        return (
            f'now published with several types {types}: '
            f'only {self.recording.bag.topic_type(name)} is recorded'
        )

    def take(self, topic: str, data: bytes, received_ns: int, source_ns: int) -> None:
        """Queue a serialized message of ``topic``. Log time: ``received_ns`` (the
        middleware's receive time; 0: not to be used, then ``log_clock_ns()``); publish
        time: the header stamp if the topic is stamped and it is set, else ``source_ns``
        (the send time; 0: unknown), else the log time."""
        self._last_message_time = self._clock()
        log_time_ns = received_ns or self._log_clock_ns()
        publish_time_ns = (
            (header_stamp_ns(data) if self._stamped[topic] else None) or source_ns or log_time_ns
        )
        self.recording.put(topic, data, log_time_ns, publish_time_ns)

    def start_drain(self) -> float:
        """A stop was requested: the longest [s] to go on taking the backlog."""
        self._last_message_time = self._clock()
        return MAX_DRAIN_PERIOD

    def drained(self) -> bool:
        """True once no message arrived for QUIET_PERIOD: the backlog is recorded."""
        return self._clock() - self._last_message_time > QUIET_PERIOD

    def status(self, skipped: set[str]) -> tuple[str, str, dict[str, Any]]:
        """(level, message, values) of the recorder's diagnostic; ``skipped``: the topics
        that cannot be recorded."""
        # The counts are ints the writer thread updates: read without the bag lock, which
        # it holds while writing a whole batch.
        recording = self.recording
        topics, dropped = recording.topics, recording.dropped
        if recording.write_error is not None:
            level, message = 'error', f'writing failed: {recording.write_error}'
        else:
            level = 'warn' if sum(dropped.values()) or skipped else 'ok'
            message = 'closed' if recording.closed else 'recording'
        values: dict[str, Any] = {
            'bag': self.bag_path,
            'topics recorded': len(topics),
            'messages': sum(t.message_count for t in topics),
            'dropped': sum(dropped.values()),
            'bytes written': recording.bytes_written,
        }
        for topic in topics:
            values[topic.name] = f'{topic.message_count}' + (
                f' ({dropped[topic.name]} dropped)' if dropped.get(topic.name) else ''
            )
        if skipped:
            values['not recorded'] = ', '.join(sorted(skipped))
        return level, message, values

    def counts(self) -> list[str]:
        """The closing log: messages written (and dropped) per topic."""
        topics = self.recording.topics
        lines = [
            f'closed {self.bag_path}: {self.recording.bag.message_count} messages on '
            f'{len(topics)} topics'
        ]
        for topic in topics:
            dropped = self.recording.dropped.get(topic.name, 0)
            lines.append(
                f'  {topic.name}: {topic.message_count}'
                + (f' ({dropped} dropped: writer too slow)' if dropped else '')
            )
        return lines

    def never_published(self, wanted: set[str]) -> list[str]:
        """The ``wanted`` topics never recorded (no publisher of theirs was found), sorted."""
        return sorted(wanted - {t.name for t in self.recording.topics})
