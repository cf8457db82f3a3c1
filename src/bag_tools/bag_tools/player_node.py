"""``player``: replays a rosbag2 MCAP bag onto its topics with the recorded timing.

The recorded serialized bytes are published unchanged, in log-time order, message ``i`` at
``start + (log_time_i - log_time_0) / rate`` on the monotonic clock (no drift accumulates).
Topics recorded from transient-local publishers only are republished latched
(``LATCHED_QOS``), the others with ``DEFAULT_QOS``; both are reliable, so they reach
reliable and best-effort subscribers alike.

Discovery: a volatile publisher delivers nothing to a subscriber it has not matched yet, so
the first messages of a replay would be lost to discovery. Before playing, the player waits
until every publisher has at least one matched subscription (then 0.2 s more, for the
subscriber's side of the match), at most ``wait_for_subscribers`` seconds (default 5 s:
discovering a newly started process can take a few seconds here; topics nobody listens to
then simply start unheard). Once matched, the reliable middleware retransmits what a
subscriber missed while it is still in the publisher's history (the last 10 messages).
At the end the player waits (bounded) until the subscribers acknowledged everything, so
exiting does not cut off the last messages.

By default ``/rosout``, ``/parameter_events`` and ``/diagnostics`` are recorded but not
replayed (parameter ``exclude``): old log lines, parameter changes and health reports are not
inputs of any node, and would reappear on the live graph as if they were happening now.

A missing or invalid bag or parameter is reported in one log line and the process exits with
status 2 (the project's status for unusable start-up input, as ``vgm_common.node_main``).
A bag found damaged while playing (chunk bytes overwritten: chunk CRCs are checked; a file
cut short, before or while it plays) stops playback with one error line naming the file and the
messages read from it, and the process exits with status 1; nothing of the damaged chunk
is published.

/diagnostics, every ``DIAGNOSTICS_PERIOD`` and when playback ends: state, messages played /
messages of the played topics in the bag, bag time; WARN if a requested topic cannot be
played or a parameter change was refused, ERROR if reading the bag failed.
"""

import sys
import threading
from typing import Any

from rclpy.publisher import Publisher

from bag_tools.bag_writer import BagError, BagReader
from bag_tools.message_definitions import DefinitionNotFoundError, type_hash
from bag_tools.playback import Playback, PlayerSettings, bag_span, is_latched, topics_to_play
from bag_tools.topic_discovery import import_message_type
from vgm_common.errors import VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS

DIAGNOSTICS_PERIOD = 1.0  # [s]


class PlayerStartupError(VgmError):
    """The bag is unusable or holds nothing to play; the message says which and why."""


PLAYER = ConfigParams(PlayerSettings)
PARAMETERS = PLAYER.declarations()


class PlayerNode(GraphNode):
    """Publishes the messages of one bag with the recorded timing (a Playback's).

    ``finished`` is set once playback ended (or failed); ``published`` counts per topic.
    For ``vgm_common.node_main.run_node``: ``exit_requested`` is set once playback ended if
    ``exit_when_done``; ``close()``; ``exit_status`` (1 if reading the bag failed).

    Raises:
        ParameterError: invalid parameter value.
        PlayerStartupError: no/invalid bag, or nothing to play.
    """

    node_name = 'player'

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(
            PARAMETERS,
            on_change={'rate': lambda rate: self._playback.schedule.set_rate(rate)},
            **kwargs,
        )
        settings = PLAYER.build(self.params)
        self.exit_when_done = settings.exit_when_done
        try:
            self._reader = BagReader(settings.bag)
        except BagError as error:
            raise PlayerStartupError(f'cannot play {settings.bag!r}: {error}') from None
        self._topic_publishers = self._create_publishers(settings)
        self._total = sum(
            t.message_count for t in self._reader.topics if t.name in self._topic_publishers
        )  # one pass
        # [ns] bag time 0 (the first message played if the metadata does not say) and length
        self._bag_start, self._bag_duration = bag_span(self._reader.metadata)
        self.finished = threading.Event()
        self.exit_requested = threading.Event()
        self._stop = threading.Event()
        self._playback = Playback(
            settings,
            str(self._reader.path),
            self._topic_publishers,
            lambda: self._reader.messages(self._topic_publishers),
            lambda topic, data: self._topic_publishers[topic].publish(data),
            self._log,
            self._stop,
        )
        self.create_timer(DIAGNOSTICS_PERIOD, self._publish_progress)
        self._thread = threading.Thread(target=self._run, name='playback', daemon=True)
        self._thread.start()

    @property
    def published(self) -> dict[str, int]:
        """Messages published per topic."""
        return self._playback.published

    @property
    def error(self) -> Exception | None:
        """Why reading the bag failed, or None."""
        return self._playback.error

    @property
    def exit_status(self) -> int:
        """The process exit status: 1 if reading the bag failed, else 0."""
        return 0 if self.error is None else 1

    def _log(self, level: str, text: str) -> None:
        getattr(self.get_logger(), level)(text)

    def _create_publishers(self, settings: PlayerSettings) -> dict[str, Publisher]:
        recorded = {t.name: t for t in self._reader.topics}
        names, self._not_played = topics_to_play(recorded, settings.topics, settings.exclude)
        for name in self._not_played:
            self.get_logger().warning(f'topic {name} is not in the bag')
        publishers = {}
        for name in names:
            info = recorded[name]
            try:
                message_type = import_message_type(info.type)
            except (ImportError, AttributeError, ValueError) as error:
                self._not_played[name] = f'type {info.type} is not installed'
                self.get_logger().warning(
                    f'not playing {name}: type {info.type} is not installed ({error})'
                )
                continue
            try:
                local_hash = type_hash(info.type)
            except DefinitionNotFoundError:
                local_hash = ''
            if (
                info.type_description_hash
                and local_hash
                and info.type_description_hash != local_hash
            ):
                self.get_logger().warning(
                    f'{name}: recorded {info.type} differs from the installed definition '
                    f'({info.type_description_hash} != {local_hash}); playing the bytes as is'
                )
            latched = is_latched(info)
            publishers[name] = self.create_publisher(
                message_type, name, LATCHED_QOS if latched else DEFAULT_QOS
            )
            self.get_logger().info(
                f'playing {name} [{info.type}] {info.message_count} messages'
                + (' (latched)' if latched else '')
            )
        if not publishers:
            raise PlayerStartupError(
                f'nothing to play in {self._reader.path}: no recorded topic matches topics/exclude'
            )
        return publishers

    def _unheard(self) -> list[str]:
        """The topics played that no subscriber matched yet."""
        return [n for n, p in self._topic_publishers.items() if p.get_subscription_count() == 0]

    def _run(self) -> None:  # playback thread
        try:
            self._playback.run(self._unheard)
        finally:
            self.finished.set()
            if self.exit_when_done:
                self.exit_requested.set()  # run_node's close() joins this thread first
            if self.context.ok():
                self._publish_progress()

    def _publish_progress(self) -> None:
        rejected = dict(self.diagnostics.rejected)  # updated by the executor thread
        self.diagnostics.publish(
            'playback',
            *self._playback.progress(
                self._total, self._bag_start, self._bag_duration, self._not_played, rejected
            ),
        )

    # -- shutdown ------------------------------------------------------------------------

    def stop(self) -> None:
        """Stop playback and wait for the playback thread. Idempotent."""
        self._stop.set()
        self._thread.join()

    def close(self) -> None:
        """For run_node: stop playback before the node is destroyed."""
        self.stop()


def main(args: list[str] | None = None) -> int:
    """Play the bag; returns the exit status: 0 = played (or stopped by SIGINT/SIGTERM),
    1 = the bag failed while reading, 2 = unusable bag or parameter at start-up."""
    return run_node(PlayerNode, args)


if __name__ == '__main__':
    sys.exit(main())
