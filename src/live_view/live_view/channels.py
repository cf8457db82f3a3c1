"""live_view's state without ROS: the settings that are the one source of its server
parameters, and the channel table: the topics advertised, the clients watching each,
which topics must be subscribed in ROS, the last latched message, the camera transforms
and the counts its diagnostic reports. Called from the executor's and the server's
threads (a lock of its own)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from vgm_common.settings import setting


@dataclass(frozen=True)
class ServerSettings:
    """Where live_view serves and how much it queues: the one source of these parameters."""

    address: str = setting(
        '127.0.0.1',
        'Address the WebSocket server listens on; 0.0.0.0 opens it to the network (on '
        'purpose: anyone there can watch).',
        read_only=True,
    )
    port: int = setting(
        8765,
        "TCP port of the WebSocket server (foxglove_bridge's); 0 = any free port (logged).",
        range=(0, 65535),
        read_only=True,
    )
    message_backlog_size: int = setting(
        300,
        'Messages queued per client at most; a slow client loses the oldest beyond this '
        '(10 s of three 30 Hz cameras).',
        range=(1, 100000),
        read_only=True,
    )


class Channel(Protocol):
    """What the table needs of a foxglove channel (``foxglove.Channel``)."""

    def has_sinks(self) -> bool:
        """True while some client subscribes to it."""
        ...

    def log(self, data: bytes, *, log_time: int | None = None) -> None:
        """Send ``data`` [serialized] to its subscribers, with ``log_time`` [ns]."""
        ...


@dataclass
class Forwarded:
    """One advertised topic: its foxglove channel, how to subscribe to it in ROS
    (``message_type``, ``qos``: opaque here), that subscription while some client watches
    the topic, the last message if latched, and counts."""

    channel: Channel
    type_name: str  # pkg/msg/Type
    message_type: Any
    qos: Any
    latched: bool  # subscribed transient-local: its last message is kept
    subscription: Any = None
    last: tuple[bytes, int] | None = None  # (data, log time [ns])
    received: int = 0
    forwarded: int = 0


class ChannelTable:
    """The advertised topics and the clients watching them. ``clock_ns`` (wall clock
    [ns]) times a message the middleware did not."""

    def __init__(self, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self._lock = threading.Lock()  # the server's threads and the executor's
        self._clock_ns = clock_ns
        self._forwarded: dict[str, Forwarded] = {}
        self._mixed_types: set[str] = set()  # served topics that gained another type
        self._client_topics: dict[int, set[str]] = {}  # client id -> topics it watches
        self._camera_transforms: dict[str, Any] = {}  # camera frame -> its transform
        self.transforms_sent = 0

    def __contains__(self, topic: object) -> bool:
        with self._lock:
            return topic in self._forwarded

    def add(self, topic: str, forwarded: Forwarded) -> None:
        """Advertise ``topic`` (its channel was created)."""
        with self._lock:
            self._forwarded[topic] = forwarded

    def new_second_type(self, topic: str, types: list[str]) -> str | None:
        """Why ``topic``'s messages of other types than its channel's are not served, the
        first time it has several ``types``; else None. (Another process: DDS refuses it
        within one.)"""
        with self._lock:
            if len(types) <= 1 or topic in self._mixed_types:
                return None
            self._mixed_types.add(topic)
            type_name = self._forwarded[topic].type_name
        return f'now published with several types {types}: only {type_name} is served'

    # -- clients (server threads) ----------------------------------------------------------

    def client_subscribed(self, client_id: int, topic: str) -> None:
        """Client ``client_id`` watches ``topic``; a latched topic already subscribed in
        ROS sends its last message again (everyone subscribed gets it again: harmless for
        a latched value)."""
        with self._lock:
            self._client_topics.setdefault(client_id, set()).add(topic)
            forwarded = self._forwarded.get(topic)
        if forwarded is not None and forwarded.subscription is not None and forwarded.last:
            data, log_time_ns = forwarded.last
            forwarded.channel.log(data, log_time=log_time_ns)

    def client_unsubscribed(self, client_id: int, topic: str) -> None:
        """Client ``client_id`` no longer watches ``topic``."""
        with self._lock:
            topics = self._client_topics.get(client_id, set())
            topics.discard(topic)
            if not topics:
                self._client_topics.pop(client_id, None)

    # -- ROS subscriptions and messages (executor thread) ------------------------------------

    def update_subscriptions(
        self,
        subscribe: Callable[[str, Forwarded], Any],
        unsubscribe: Callable[[Any], object],
    ) -> None:
        """Subscribe in ROS (``subscribe(topic, forwarded)`` returns the subscription) to
        what some client watches, and ``unsubscribe`` what nobody does any more (as
        foxglove_bridge): an unwatched image costs the graph nothing."""
        with self._lock:
            watched = set().union(*self._client_topics.values())
            forwarded = dict(self._forwarded)
        for topic, f in forwarded.items():
            if topic in watched and f.subscription is None:
                # A transient-local subscription receives the latched value again.
                f.subscription = subscribe(topic, f)
            elif topic not in watched and f.subscription is not None:
                unsubscribe(f.subscription)
                f.subscription = None

    def forward(self, forwarded: Forwarded, data: bytes, received_ns: int) -> None:
        """A message of ``forwarded``'s topic, received at ``received_ns`` [ns] (0: not
        known, then now): kept if latched, sent if some client watches."""
        log_time_ns = received_ns or self._clock_ns()
        forwarded.received += 1
        if forwarded.latched:
            forwarded.last = (data, log_time_ns)
        if forwarded.channel.has_sinks():  # some client subscribed to it
            forwarded.channel.log(data, log_time=log_time_ns)
            forwarded.forwarded += 1

    # -- frame transforms --------------------------------------------------------------------

    def set_camera_transform(self, frame: str, transform: Any) -> None:
        """The latest transform base_link -> camera ``frame``."""
        with self._lock:
            self._camera_transforms[frame] = transform

    def camera_transforms(self) -> list[Any]:
        """The cameras' latest transforms."""
        with self._lock:
            return list(self._camera_transforms.values())

    # -- diagnostics -------------------------------------------------------------------------

    def status(
        self, url: str, backlog: int, skipped: set[str], rejected: int
    ) -> tuple[str, str, dict[str, Any]]:
        """(level, message, values) of live_view's diagnostic: served at ``url`` with
        ``backlog`` messages per client at most; ``skipped`` topics cannot be served;
        ``rejected`` inputs so far."""
        with self._lock:
            forwarded = dict(self._forwarded)
            clients = len(self._client_topics)
        values: dict[str, Any] = {
            'url': url,
            'clients': clients,
            'channels': len(forwarded) + 1,  # and /tf
            'transforms sent': self.transforms_sent,
            'backlog per client': backlog,
        }
        for topic, f in sorted(forwarded.items()):
            values[topic] = f'{f.forwarded} forwarded of {f.received}'
        if skipped:
            values['not served'] = ', '.join(sorted(skipped))
        level = 'warn' if skipped or rejected else 'ok'
        return level, f'{clients} client(s), {len(forwarded)} topics', values
