"""The player without ROS: the settings that are the one source of its parameters, the
topics it plays, and when it publishes each message. Bag time ``t`` is played at
``start + (t - t_0) / rate`` on a monotonic clock, so no drift accumulates however long
the bag; a rate change re-anchors at the bag time reached, so playback neither jumps nor
stalls; a message already due is published at once (a late player catches up)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from bag_tools.bag_writer import BagError, BagMessage, TopicInfo
from vgm_common.settings import setting
from vgm_common.topics import DIAGNOSTICS_TOPIC

MAX_SLEEP = 0.05  # [s] sleep slices, so a rate change or a stop takes effect promptly
MATCH_SETTLE = 0.2  # [s] after every publisher has matched a subscriber, before playing
MATCH_POLL = 0.02  # [s] how often the match is checked while waiting for it
MIN_RATE, MAX_RATE = 1e-3, 1e3  # playback speed factors accepted


class PlaybackClock:
    """The schedule of a playback at ``rate`` (1 = recorded pace), on ``clock`` [s]."""

    def __init__(self, rate: float, clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._clock = clock
        self.rate = rate
        # Bag time _anchor_bag [ns] is played at clock time _anchor_wall [s].
        self._anchor_wall: float | None = None
        self._anchor_bag: int | None = None

    def start(self, bag_time_ns: int) -> None:
        """Play ``bag_time_ns`` now (the first message of a pass)."""
        with self._lock:
            self._anchor_wall, self._anchor_bag = self._clock(), bag_time_ns

    def set_rate(self, rate: float) -> None:
        """Play at ``rate`` from the bag time reached now."""
        with self._lock:
            if self._anchor_wall is not None and self._anchor_bag is not None:
                now = self._clock()
                self._anchor_bag += int((now - self._anchor_wall) * self.rate * 1e9)
                self._anchor_wall = now
            self.rate = rate

    def due_in(self, log_time_ns: int) -> float:
        """[s] until the message of ``log_time_ns`` is due (<= 0: publish it now)."""
        with self._lock:
            if self._anchor_wall is None or self._anchor_bag is None:
                raise RuntimeError('PlaybackClock.start() first')
            due = self._anchor_wall + (log_time_ns - self._anchor_bag) / 1e9 / self.rate
            return due - self._clock()


def _required(value: str) -> str | None:
    return None if value else 'is required: the bag directory to play'


@dataclass(frozen=True)
class PlayerSettings:
    """What the player plays and how: the one source of these parameters."""

    bag: str = setting(
        '',
        'Path of the bag directory (the one holding metadata.yaml).',
        check=_required,
        read_only=True,
    )
    rate: float = setting(
        1.0,
        'Playback speed factor (2 = twice as fast); may be changed while playing.',
        range=(MIN_RATE, MAX_RATE),
    )
    loop: bool = setting(False, 'Play the bag again and again.', read_only=True)
    topics: tuple[str, ...] = setting(
        (), 'Topics to play (exact names); empty = every recorded topic.', read_only=True
    )
    exclude: tuple[str, ...] = setting(
        ('/rosout', '/parameter_events', DIAGNOSTICS_TOPIC),
        'Recorded topics not to play (exact names); [] = none.',
        read_only=True,
    )
    exit_when_done: bool = setting(
        True,
        'Exit once the bag was played; false keeps latched topics available.',
        read_only=True,
    )
    wait_for_subscribers: float = setting(
        5.0,
        'Before playing, wait at most this long for every topic to have a subscriber, so '
        'the first messages are not lost to discovery; 0 = do not wait.',
        unit='s',
        range=(0.0, 3600.0),
        read_only=True,
    )


def is_latched(topic_info: TopicInfo) -> bool:
    """True if every recorded publisher of the topic offered transient-local durability."""
    profiles = topic_info.offered_qos_profiles
    return bool(profiles) and all(p.get('durability') == 'transient_local' for p in profiles)


def topics_to_play(
    recorded: Iterable[str], wanted: Iterable[str], excluded: Iterable[str]
) -> tuple[list[str], dict[str, str]]:
    """(the recorded topics to play, in the bag's order: those ``wanted`` (all if none)
    and not ``excluded``; {wanted topic: why it is not played} for those not in the bag)."""
    recorded, wanted, excluded = list(recorded), set(wanted), set(excluded)
    names = [n for n in recorded if (not wanted or n in wanted) and n not in excluded]
    missing = {name: 'not in the bag' for name in sorted(wanted - set(recorded))}
    return names, missing


def bag_span(metadata: Mapping[str, Any] | None) -> tuple[int | None, int | None]:
    """(start [ns since epoch], duration [ns]) of a bag from its metadata; (None, None)
    for a bag recovered without metadata (None, or without those keys)."""
    if metadata is None:
        return None, None
    try:
        return (
            int(metadata['starting_time']['nanoseconds_since_epoch']),
            int(metadata['duration']['nanoseconds']),
        )
    except (KeyError, TypeError, ValueError):
        return None, None


class Stop(Protocol):
    """What ends a playback early: ``threading.Event`` (a test's own moves its clock)."""

    def is_set(self) -> bool:
        """True once stopped."""
        ...

    def wait(self, timeout: float) -> bool:
        """Wait until stopped, at most ``timeout`` [s]; True if stopped."""
        ...


class Playback:
    """Plays ``messages()`` (the bag ``source``'s, in log-time order) by calling ``publish(topic,
    data)`` at the recorded pace (``rate``), once or again and again (``loop``), after
    waiting for subscribers. ``clock`` (monotonic [s]) and ``stop.wait`` time it: a test
    gives a stop whose wait moves its clock. ``published`` counts per topic;
    ``state``, ``error`` (reading the bag failed) and the bag time reached say where it
    is; ``log(level, text)`` says what it did ('info', 'error')."""

    def __init__(
        self,
        settings: PlayerSettings,
        source: str,
        topics: Iterable[str],
        messages: Callable[[], Iterable[BagMessage]],
        publish: Callable[[str, bytes], None],
        log: Callable[[str, str], None],
        stop: Stop,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.schedule = PlaybackClock(settings.rate, clock)
        self._loop = settings.loop
        self._wait_for_subscribers = settings.wait_for_subscribers  # [s]
        self._source = source
        self._messages = messages
        self._publish = publish
        self._log = log
        self._stop = stop
        self._clock = clock
        self.published = dict.fromkeys(topics, 0)
        self.passes = 0
        self.state = 'waiting for subscribers'
        self.error: Exception | None = None
        self.first_log_time: int | None = None  # [ns] of the first message played
        self.bag_time: int | None = None  # [ns] log time of the last message played

    def run(self, unheard: Callable[[], list[str]]) -> None:
        """Wait (bounded) until ``unheard()`` (the topics without a subscriber) is empty,
        then play until done, stopped or failed (``error``)."""
        try:
            self._await_subscribers(unheard)
            started = self._clock()
            self.state = 'playing'
            while not self._stop.is_set():
                self.passes += 1
                if not self._play_once() or not self._loop:
                    break
            self.state = 'stopped' if self._stop.is_set() else 'done'
            self._log(
                'info',
                f'played {sum(self.published.values())} messages in '
                f'{self._clock() - started:.2f} s',
            )
        except (BagError, OSError, ValueError) as error:
            self.error = error
            self.state = 'failed'
            self._log('error', f'playing {self._source} failed: {error}')

    def _await_subscribers(self, unheard: Callable[[], list[str]]) -> None:
        if self._wait_for_subscribers <= 0:
            return
        deadline = self._clock() + self._wait_for_subscribers
        while self._clock() < deadline:
            if not unheard():
                # Our publishers matched; the subscribers' half of the match can lag a few
                # ms, and a sample sent in that gap arrives late (repaired) or not at all.
                self._stop.wait(MATCH_SETTLE)
                return
            if self._stop.wait(MATCH_POLL):
                return
        self._log(
            'info',
            f'no subscriber after {self._wait_for_subscribers:g} s on '
            f'{", ".join(sorted(unheard()))}; playing anyway',
        )

    def _play_once(self) -> bool:
        """Play the bag once; False if stopped or there was nothing to play."""
        first = True
        for message in self._messages():
            if first:
                self.schedule.start(message.log_time)
                if self.first_log_time is None:
                    self.first_log_time = message.log_time
                first = False
            if not self._sleep_until(message.log_time):
                return False
            self._publish(message.topic, bytes(message.data))
            self.published[message.topic] += 1
            self.bag_time = message.log_time
        return not first

    def _sleep_until(self, log_time_ns: int) -> bool:
        """Sleep until the clock time of ``log_time_ns``; False if stopped meanwhile."""
        while True:
            remaining = self.schedule.due_in(log_time_ns)
            if remaining <= 0:
                return not self._stop.is_set()
            if self._stop.wait(min(remaining, MAX_SLEEP)):
                return False

    def progress(
        self,
        total: int,
        bag_start: int | None,
        bag_duration: int | None,
        not_played: Mapping[str, str],
        rejected: Mapping[str, int],
    ) -> tuple[str, str, dict[str, Any]]:
        """(level, message, values) of the player's diagnostic: ``total`` messages of the
        played topics in the bag, which starts at ``bag_start`` [ns] (None: at the first
        message played) and lasts ``bag_duration`` [ns]; the requested topics
        ``not_played`` and why; parameter changes ``rejected``."""
        played = sum(self.published.values())
        values: dict[str, Any] = {
            'messages played': played,
            'messages in bag': total,
            'rate': self.schedule.rate,
        }
        if self._loop:
            values['pass'] = self.passes
        start = self.first_log_time if bag_start is None else bag_start
        if self.bag_time is not None and start is not None:
            values['bag time [s]'] = f'{(self.bag_time - start) / 1e9:.3f}'
        if bag_duration is not None:
            values['bag duration [s]'] = f'{bag_duration / 1e9:.3f}'
        for name, reason in sorted(not_played.items()):
            values[f'not played {name}'] = reason
        for what, count in rejected.items():
            values[f'rejected {what}'] = count
        if self.error is not None:
            level, message = 'error', f'failed: {self.error}'
        else:
            level = 'warn' if not_played or rejected else 'ok'
            message = f'{self.state}: {played} / {total} messages'
        return level, message, values
