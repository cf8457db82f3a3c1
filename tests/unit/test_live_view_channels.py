"""live_view's channel table without ROS or a server: which topics are subscribed in ROS
as clients come and go, what is forwarded and kept, and what the diagnostic says."""

from live_view.channels import ChannelTable, Forwarded


class RecordingChannel:
    """A foxglove channel's two calls, recorded: ``sinks`` clients subscribe to it."""

    def __init__(self, sinks=0):
        self.sinks, self.logged = sinks, []

    def has_sinks(self):
        return self.sinks > 0

    def log(self, data, *, log_time=None):
        self.logged.append((data, log_time))


def table_with(*topics, latched=()):
    """A table advertising ``topics`` (those in ``latched`` transient-local) on a wall
    clock stuck at 5000 ns."""
    table = ChannelTable(clock_ns=lambda: 5_000)
    for topic in topics:
        channel = RecordingChannel()
        table.add(topic, Forwarded(channel, 'std_msgs/msg/String', str, 'qos', topic in latched))
    return table


class Subscriptions:
    """ROS's side of update_subscriptions: the subscriptions alive, by topic."""

    def __init__(self, table):
        self.table, self.alive, self.made = table, {}, 0

    def update(self):
        self.table.update_subscriptions(self.subscribe, self.unsubscribe)
        return sorted(self.alive)

    def subscribe(self, topic, forwarded):
        self.made += 1
        self.alive[topic] = forwarded
        return topic

    def unsubscribe(self, subscription):
        del self.alive[subscription]


def test_a_topic_is_subscribed_in_ros_only_while_some_client_watches_it():
    table = table_with('/a', '/b')
    ros = Subscriptions(table)
    assert ros.update() == []  # nobody watches: nothing costs the graph
    table.client_subscribed(1, '/a')
    table.client_subscribed(2, '/a')
    table.client_subscribed(2, '/b')
    assert ros.update() == ['/a', '/b']
    assert ros.update() == ['/a', '/b'] and ros.made == 2  # not subscribed twice
    table.client_unsubscribed(1, '/a')
    assert ros.update() == ['/a', '/b']  # client 2 still watches /a
    table.client_unsubscribed(2, '/a')
    assert ros.update() == ['/b']
    table.client_unsubscribed(2, '/b')
    assert ros.update() == []
    assert table.status('ws://x', 300, set(), 0)[2]['clients'] == 0  # both gone


def test_messages_are_sent_while_watched_and_a_latched_one_again_to_a_late_client():
    table = table_with('/plain', '/latched', latched=('/latched',))
    ros = Subscriptions(table)
    table.client_subscribed(1, '/plain')
    table.client_subscribed(1, '/latched')
    ros.update()
    plain, latched = ros.alive['/plain'], ros.alive['/latched']
    table.forward(plain, b'unwatched', 1_000)  # subscribed, but the client left the channel
    plain.channel.sinks = latched.channel.sinks = 1
    table.forward(plain, b'p', 2_000)
    table.forward(latched, b'l', 0)  # no receive time: the wall clock's
    assert plain.channel.logged == [(b'p', 2_000)]
    assert latched.channel.logged == [(b'l', 5_000)]
    assert plain.last is None and latched.last == (b'l', 5_000)
    table.client_subscribed(2, '/latched')  # a late viewer gets the latched value
    table.client_subscribed(2, '/plain')  # but no old plain message
    assert latched.channel.logged == [(b'l', 5_000)] * 2
    assert plain.channel.logged == [(b'p', 2_000)]
    level, message, values = table.status('ws://127.0.0.1:8765', 300, set(), 0)
    assert (level, message) == ('ok', '2 client(s), 2 topics')
    assert values['/plain'] == '1 forwarded of 2' and values['/latched'] == '1 forwarded of 1'
    assert values['channels'] == 3  # and /tf


def test_a_second_type_is_said_once_and_skipped_topics_warn():
    table = table_with('/a')
    assert '/a' in table and '/b' not in table
    assert table.new_second_type('/a', ['std_msgs/msg/String']) is None
    reason = table.new_second_type('/a', ['std_msgs/msg/String', 'std_msgs/msg/Int32'])
    assert reason.endswith('only std_msgs/msg/String is served')
    assert table.new_second_type('/a', ['std_msgs/msg/String', 'std_msgs/msg/Int32']) is None
    level, _, values = table.status('ws://x', 300, {'/z', '/y'}, 1)
    assert level == 'warn' and values['not served'] == '/y, /z'
    table.set_camera_transform('left', 'T1')
    table.set_camera_transform('left', 'T2')  # the latest replaces the older
    table.set_camera_transform('right', 'T3')
    assert table.camera_transforms() == ['T2', 'T3']
