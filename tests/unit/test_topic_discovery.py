"""The recorder's and live_view's topic discovery against a graph the test writes (a
stand-in for the node's graph queries): which topics are taken, skipped for good (with
one warning each) or left for a later poll."""

from types import SimpleNamespace

from bag_tools.topic_discovery import TopicDiscovery


class Graph:
    """What TopicDiscovery asks of its node: topics with their types, each topic's
    publishers, and a logger (warnings kept)."""

    def __init__(self, topics, publishers):
        self.topics, self.publishers, self.warnings = topics, publishers, []

    def get_topic_names_and_types(self):
        return list(self.topics.items())

    def get_publishers_info_by_topic(self, name):
        return self.publishers.get(name, [])

    def get_logger(self):
        return SimpleNamespace(warning=self.warnings.append)


def selection(topics=(), exclude=(), include_hidden_topics=False):
    return SimpleNamespace(
        topics=list(topics), exclude=list(exclude), include_hidden_topics=include_hidden_topics
    )


STRING = ['std_msgs/msg/String']


def test_published_wanted_topics_of_one_installed_type_are_taken_once():
    graph = Graph(
        {
            '/a': STRING,
            '/_hidden/b': STRING,
            '/ns/_c': STRING,
            '/excluded': STRING,
            '/only_subscribed': STRING,
            '/two_types': ['std_msgs/msg/String', 'std_msgs/msg/Int32'],
            '/not_installed': ['nope_msgs/msg/Nothing'],
        },
        publishers={
            name: ['publisher']
            for name in ('/a', '/_hidden/b', '/ns/_c', '/excluded', '/two_types', '/not_installed')
        },
    )
    discovery = TopicDiscovery(graph, selection(exclude=['/excluded']), 'recording')
    found = discovery.poll(taken=set())
    assert [t.name for t in found] == ['/a']
    (a,) = found
    assert a.type_name == 'std_msgs/msg/String' and a.publishers == ['publisher']
    assert a.message_type.__name__ == 'String'
    assert a.definition[0] == 'ros2msg' and 'string data' in a.definition[1]
    assert discovery.skipped == {'/two_types', '/not_installed'}
    assert len(graph.warnings) == 2
    assert any(
        w.startswith('not recording /two_types: published with several types')
        for w in graph.warnings
    )
    assert discovery.poll(taken={'/a'}) == [] and len(graph.warnings) == 2  # said once
    graph.publishers['/only_subscribed'] = ['publisher']  # a publisher came: taken now
    assert [t.name for t in discovery.poll(taken={'/a'})] == ['/only_subscribed']


def test_listed_topics_hidden_ones_and_the_types_of_taken_topics():
    graph = Graph(
        {'/a': STRING, '/b': STRING, '/_h': STRING}, {n: [1] for n in ('/a', '/b', '/_h')}
    )
    listed = TopicDiscovery(graph, selection(topics=['/b', '/never']), 'serving')
    assert [t.name for t in listed.poll(taken=set())] == ['/b']
    assert not listed.wanted('/a') and listed.wanted('/never')
    hidden_too = TopicDiscovery(graph, selection(include_hidden_topics=True), 'serving')
    assert [t.name for t in hidden_too.poll(taken=set())] == ['/a', '/b', '/_h']
    seen = []
    graph.topics['/a'] = ['std_msgs/msg/String', 'std_msgs/msg/Int32']
    hidden_too.poll(taken={'/a'}, on_types_of_taken=lambda name, types: seen.append((name, types)))
    assert seen == [('/a', ['std_msgs/msg/String', 'std_msgs/msg/Int32'])]
