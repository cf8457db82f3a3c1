"""vgm_common's node edges (parameters, graph_node, diagnostics, subscriber_gate,
node_main) with real rclpy nodes in this process: NodeParameters (kinds,
ranges, lists, refusals with a reason, the on_change hook) and run_node (exit request,
drain after a signal, exit status, one-line start-up error)."""

import array
import os
import signal
import threading
from dataclasses import dataclass

import pytest
import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from harness import wait_for
from vgm_common.diagnostics import Diagnostics, guarded
from vgm_common.node_main import run_node
from vgm_common.parameters import (
    ConfigParams,
    NodeParameters,
    Param,
    ParameterError,
    params_file_section_warnings,
)
from vgm_common.subscriber_gate import SubscriberGate


@pytest.fixture
def private_domain(ros_env, monkeypatch):
    """This process on the test's private domain."""
    for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE'):
        monkeypatch.setenv(key, ros_env[key])


@pytest.fixture
def make_node(private_domain):
    """``make_node(**overrides)``: a node in its own context with parameter overrides."""
    context = rclpy.Context()
    rclpy.init(context=context)
    nodes = []

    def _make(**overrides):
        node = Node(
            f'probe_{len(nodes)}',
            context=context,
            parameter_overrides=[
                Parameter(name, value=value) for name, value in overrides.items()
            ],
        )
        nodes.append(node)
        return node

    yield _make
    for node in nodes:
        node.destroy_node()
    rclpy.shutdown(context=context)


def probe_params():
    """Parameters of every kind."""
    return [
        Param('rate', 30.0, '[Hz]', range=(0.0, 200.0)),
        Param('count', 3, 'How many.', range=(1, 10)),
        Param('mode', 'fast', 'How.', choices=('fast', 'exact')),
        Param(
            'names',
            ['/a'],
            'Topic names.',
            check=lambda names: None
            if all(n.startswith('/') for n in names)
            else 'must be absolute',
        ),
        Param('weights', [1.0, 2.0], 'Diagonal of W.'),
        Param('frozen', 'x', 'Fixed at start-up.', read_only=True),
    ]


def refusal(node, name, value):
    """The reason a change is refused; '' if it was accepted."""
    result = node.set_parameters([Parameter(name, value=value)])[0]
    return '' if result.successful else result.reason


def test_start_up_values_take_the_declared_kind(make_node):
    params = NodeParameters(make_node(rate=100, weights=[3, 4], names=[]), probe_params())
    assert params.rate == 100.0 and isinstance(params.rate, float)  # `rate:=100`
    assert params.weights == [3.0, 4.0] and all(isinstance(w, float) for w in params.weights)
    assert params.names == [] and params.count == 3 and params.mode == 'fast'


def test_an_empty_list_parameter_has_a_value(make_node):
    node = make_node()
    NodeParameters(node, [Param('topics', [], 'Topic names.', read_only=True)])
    # What the get_parameters service answers (it answers nothing for an unset one).
    assert node.get_parameter('topics').value == []
    assert node.get_parameter('topics').type_ == Parameter.Type.STRING_ARRAY
    assert 'read-only' in refusal(node, 'topics', ['/a'])


@pytest.mark.parametrize(
    'overrides, reason',
    [
        ({'rate': 'fast'}, 'expected float'),
        ({'rate': 500.0}, 'out of range'),  # the descriptor's floating-point range
        ({'rate': float('nan')}, 'out of range'),
        ({'count': 2.5}, 'count'),
        ({'count': 11}, 'out of range'),  # refused by rclpy itself: the descriptor's range
        ({'mode': 'slow'}, 'not one of fast, exact'),
        ({'names': 'a'}, 'expected a list'),
        ({'names': ['a']}, 'must be absolute'),
        ({'weights': [True, False]}, 'expected a list of float'),
    ],
)
def test_a_bad_start_up_value_is_one_line_naming_the_parameter(make_node, overrides, reason):
    ((name, value),) = overrides.items()
    with pytest.raises(ParameterError) as raised:
        NodeParameters(make_node(**overrides), probe_params())
    message = str(raised.value)
    assert message.startswith(f'parameter {name!r}: ') and reason in message
    assert '\n' not in message and raised.value.key == name


def one_weight_per_count(values):
    if len(values['weights']) != values['count']:
        return f"'weights' needs {values['count']} values"
    return None


def test_a_value_for_a_name_not_declared_is_never_dropped_silently(make_node, capfd):
    # A name from before a rename: a start-up error that names the new one.
    with pytest.raises(ParameterError, match="'speed' is now 'rate'"):
        NodeParameters(make_node(speed=5.0), probe_params(), renamed={'speed': 'rate'})
    # Any other: a warning naming it; the node starts with its defaults.
    params = NodeParameters(make_node(rat=5.0, count=4), probe_params())
    assert params.rate == 30.0 and params.count == 4
    assert 'ignored, not parameters of this node: rat' in capfd.readouterr().err
    with pytest.raises(ValueError, match='undeclared'):
        NodeParameters(make_node(), probe_params(), renamed={'speed': 'rates'})


def test_a_name_near_a_declared_one_is_suggested(make_node, capfd):
    NodeParameters(make_node(rat=5.0, colour=1), probe_params())
    assert (
        'ignored, not parameters of this node: colour, rat (did you mean rate?)'
        in capfd.readouterr().err
    )


@pytest.mark.parametrize(
    'content, warning',
    [
        # Written for another node: rcl starts this one on its defaults without a word.
        (
            'sfs_stereo_node:\n  ros__parameters:\n    window: 7\n',
            'has no section for /curve_recon_node (its sections: sfs_stereo_node)',
        ),
        (
            '/**:\n  ros__parameters:\n    window: 7\n    albedo: 0.8\n'
            'sfs_stereo_node:\n  ros__parameters:\n    fusion: x\n',
            'its section /** holds no parameter of /curve_recon_node '
            '(its sections: /**, sfs_stereo_node)',
        ),
        ('curve_recon_node:\n  ros__parameters:\n    degree: 3\n', None),
        ('/**:\n  ros__parameters:\n    degree: 3\n    window: 7\n', None),
        ('/**/curve_recon_node:\n  ros__parameters:\n    method:\n      x: 1\n', None),
    ],
)
def test_a_params_file_with_nothing_for_the_node_is_a_warning_naming_its_sections(
    tmp_path, content, warning
):
    path = tmp_path / 'params.yaml'
    path.write_text(content)
    declared = {'degree', 'method.x', 'use_sim_time'}.__contains__
    warnings = params_file_section_warnings(path, '/curve_recon_node', declared)
    if warning is None:
        assert warnings == []
    else:
        assert len(warnings) == 1 and warning in warnings[0] and str(path) in warnings[0]


def test_values_that_must_go_together_are_checked_at_start_up_and_on_change(make_node):
    with pytest.raises(ParameterError, match="parameters: 'weights' needs 3 values"):
        NodeParameters(make_node(), probe_params()).add_check(one_weight_per_count)
    node = make_node(count=2)
    diagnostics = Diagnostics(node)
    params = NodeParameters(node, probe_params(), diagnostics=diagnostics)
    params.add_check(one_weight_per_count)
    assert "'weights' needs 2 values" in refusal(node, 'weights', [1.0, 2.0, 3.0])
    assert "'weights' needs 3 values" in refusal(node, 'count', 3)
    assert (params.weights, params.count) == ([1.0, 2.0], 2)  # nothing changed
    # Both at once: judged together.
    result = node.set_parameters_atomically(
        [Parameter('count', value=3), Parameter('weights', value=[1.0, 2.0, 3.0])]
    )
    assert result.successful, result.reason
    assert (params.weights, params.count) == ([1.0, 2.0, 3.0], 3)
    assert diagnostics.rejected == {'parameter change': 2}


@dataclass(frozen=True)
class ProbeSettings:
    rate: float = 30.0
    gains: tuple[float, float] = (1.0, 2.0)
    internal: int = 7  # no parameter fills it


def test_config_params_fill_a_core_s_settings_from_the_current_values(make_node):
    settings = ConfigParams(ProbeSettings, renamed={'gains': 'weights'})
    node = make_node(rate=50)
    params = NodeParameters(node, probe_params())
    assert settings.build(params) == ProbeSettings(rate=50.0, gains=(1.0, 2.0))
    assert refusal(node, 'weights', [3.0, 4.0]) == ''
    assert settings.fields(params) == {'rate': 50.0, 'gains': (3.0, 4.0)}  # tuple, as the core's
    # A renamed field naming no field or no parameter would silently do nothing.
    for renamed in ({'gains': 'weight'}, {'gain': 'weights'}):
        with pytest.raises(ValueError, match='no such field or parameter'):
            ConfigParams(ProbeSettings, renamed=renamed).build(params)


def test_changes_are_checked_then_applied_and_reported(make_node):
    node = make_node()
    changes = []
    vetoed = False  # a callback added before ours, so it runs after ours (rclpy's order)
    node.add_on_set_parameters_callback(
        lambda parameters: SetParametersResult(successful=not vetoed, reason='veto')
    )
    diagnostics = Diagnostics(node)
    on_change = {'rate': lambda value: changes.append(('rate', value))}
    params = NodeParameters(node, probe_params(), diagnostics, on_change)

    assert refusal(node, 'rate', 50) == ''  # an int for a float
    assert params.rate == 50.0 and changes == [('rate', 50.0)]
    # A numeric array arrives from the parameter service as array('d').
    assert refusal(node, 'weights', array.array('d', [5.0, 6.0])) == ''
    assert params.weights == [5.0, 6.0] and isinstance(params.weights, list)

    assert 'rate out of range' in refusal(node, 'rate', 500.0)  # rclpy's, by the descriptor
    assert "parameter 'rate'" in refusal(node, 'rate', 'fast')  # dynamic typing: ours to refuse
    assert "parameter 'mode'" in refusal(node, 'mode', 'slow')
    assert refusal(node, 'frozen', 'y')  # read-only
    assert params.rate == 50.0 and params.mode == 'fast' and params.frozen == 'x'
    assert changes == [('rate', 50.0)]
    assert diagnostics.rejected == {'parameter change': 2}  # the two refused by our check

    # Another callback vetoes after ours accepted: the change never happened, so nothing
    # is applied.
    vetoed = True
    assert refusal(node, 'rate', 60.0) == 'veto'
    assert params.rate == 50.0 and changes == [('rate', 50.0)]
    # A hook on a name never declared would never run: a programming error.
    with pytest.raises(ValueError, match='undeclared'):
        NodeParameters(make_node(), probe_params(), on_change={'rates': changes.append})


class _Ticker(Node):
    """Counts timer ticks; what run_node calls is recorded in ``log`` (a class attribute,
    as run_node constructs the node itself)."""

    node_name = 'ticker'
    period = 0.01  # [s]
    log = []

    def __init__(self):
        super().__init__(self.node_name)
        self.ticks = 0
        self.exit_requested = threading.Event()
        self.exit_status = 0
        self.create_timer(self.period, self._tick)

    def _tick(self):
        self.ticks += 1
        self.on_tick()

    def on_tick(self):
        pass

    def close(self):
        self.log.append(('close', self.ticks))


def test_guarded_callbacks_never_raise_and_a_service_answers_failure():
    from std_srvs.srv import Trigger

    class Rejections:
        def __init__(self):
            self.seen = []

        def reject(self, what, reason):
            self.seen.append((what, reason))

    class Plain:  # reported as rejected input
        diagnostics = Rejections()

        @guarded('image')
        def on_image(self, msg):
            raise ValueError(f'bad {msg}')

    class WithHandler:  # handed to the node's own handler (pa10_ik_node holds the arm)
        errors = []

        def on_internal_error(self, what, error):
            self.errors.append((what, str(error)))

        @guarded('start')
        def on_start(self, request, response):
            raise RuntimeError('no waypoints')

    plain = Plain()
    assert plain.on_image('x') is None
    assert plain.diagnostics.seen == [('image', 'ValueError: bad x')]
    node = WithHandler()
    response = node.on_start(Trigger.Request(), Trigger.Response(success=True))
    assert not response.success and response.message == 'start: no waypoints'
    assert node.errors == [('start', 'no waypoints')]


def test_subscriber_gate_opens_on_matched_subscribers_or_after_its_timeout(make_node):
    from std_msgs.msg import String

    from vgm_common.qos import DEFAULT_QOS

    node = make_node()
    publisher = node.create_publisher(String, '/gated', DEFAULT_QOS)
    gate = SubscriberGate(node, [publisher], min_subscribers=1, timeout=60.0)
    assert not gate.is_open() and not gate.opened.is_set()
    node.create_subscription(String, '/gated', lambda msg: None, DEFAULT_QOS)
    wait_for(gate.is_open, 10.0, 'the gate to open on a matched subscriber', interval=0.01)
    assert gate.opened.is_set() and gate.is_open()  # open for good
    lonely = node.create_publisher(String, '/nobody_listens', DEFAULT_QOS)
    assert SubscriberGate(node, [lonely], 1, timeout=0.0).is_open()  # waited long enough


def test_subscriber_gate_waits_for_the_named_node_on_every_stream(make_node):
    """The demo's failure: sensor_sim's count of camera subscribers was met by the pipeline
    while the recorder was still starting, and the first joint states were lost."""
    from std_msgs.msg import String

    from vgm_common.qos import DEFAULT_QOS

    gated = make_node()  # probe_0
    camera = gated.create_publisher(String, '/gated/camera', DEFAULT_QOS)
    stream = gated.create_publisher(String, '/gated/stream', DEFAULT_QOS)
    gate = SubscriberGate(
        gated, [camera, stream], 1, 60.0, wait_for_nodes=['probe_2'], counted=[camera]
    )
    pipeline, recorder = make_node(), make_node()  # probe_1, probe_2
    pipeline.create_subscription(String, '/gated/camera', lambda msg: None, DEFAULT_QOS)
    wait_for(camera.get_subscription_count, 10.0, 'the pipeline subscriber', interval=0.01)
    assert not gate.is_open()  # the count is met, the recorder is not there
    assert 'probe_2 on /gated/stream' in gate.missing()
    recorder.create_subscription(String, '/gated/camera', lambda msg: None, DEFAULT_QOS)
    wait_for(lambda: camera.get_subscription_count() == 2, 10.0, 'the recorder subscriber', 0.01)
    assert not gate.is_open() and gate.missing() == ['probe_2 on /gated/stream']
    recorder.create_subscription(String, '/gated/stream', lambda msg: None, DEFAULT_QOS)
    wait_for(gate.is_open, 10.0, 'the gate to open on the recorder on every stream', 0.01)
    assert stream.get_subscription_count() == 1 and gate.missing() == []
    # A node that never comes: open after the timeout all the same.
    assert SubscriberGate(gated, [stream], 0, timeout=0.0, wait_for_nodes=['absent']).is_open()


def test_run_node_ends_on_the_node_s_exit_request_with_its_status(private_domain):
    class Finisher(_Ticker):
        log = []

        def on_tick(self):
            if self.ticks == 3:  # done, with a failure to report
                self.exit_status = 1
                self.exit_requested.set()

    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    assert run_node(Finisher, args=[]) == 1
    assert Finisher.log == [('close', 3)]
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers


def test_run_node_drains_after_a_signal_then_closes(private_domain):
    drain_period = 0.3  # [s]

    class Drained(_Ticker):
        log = []

        def on_tick(self):
            if self.ticks == 3:
                os.kill(os.getpid(), signal.SIGTERM)  # raises KeyboardInterrupt here

        def drain(self):
            self.log.append(('drain', self.ticks))
            return drain_period

    assert run_node(Drained, args=[]) == 0
    (what, at_signal), (closed, at_close) = Drained.log
    assert (what, at_signal, closed) == ('drain', 3, 'close')
    # The timer kept running while draining (bounded: no more than the period allows).
    assert 5 <= at_close - at_signal <= drain_period / _Ticker.period + 3


def test_run_node_reports_a_bad_parameter_in_one_line(private_domain, capfd):
    class Configured(_Ticker):
        log = []

        def __init__(self):
            super().__init__()
            self.params = NodeParameters(self, probe_params())

    status = run_node(Configured, args=['probe', '--ros-args', '-p', 'rate:=fast'])
    captured = capfd.readouterr()
    output = captured.out + captured.err
    errors = [line for line in output.splitlines() if '[ERROR]' in line]
    assert status == 2 and Configured.log == []
    assert len(errors) == 1 and 'Traceback' not in output, output
    assert "[ticker]: start-up error: parameter 'rate': expected float" in errors[0]


@pytest.mark.parametrize(
    'content, reason',
    [
        (None, 'cannot read params file'),
        ('ticker: [\n', 'is not valid YAML (line 2)'),
        ('- a\n- b\n', 'must map node names'),
        # YAML that only rcl's parser refuses (rcl's own 'Failed to parse global arguments'
        # line is held back)
        ('ticker:\n  rate: 3\n', 'Cannot have a value before ros__parameters'),
        ('ticker:\n  ros__parameters:\n    names: [1, "a"]\n', 'Sequence should be of same type'),
    ],
)
def test_run_node_reports_a_bad_params_file_in_one_line(
    private_domain, capfd, tmp_path, content, reason
):
    path = tmp_path / 'params.yaml'
    if content is not None:
        path.write_text(content)
    status = run_node(_Ticker, args=['probe', '--ros-args', '--params-file', str(path)])
    captured = capfd.readouterr()
    output = (captured.out + captured.err).strip()
    assert status == 2 and len(output.splitlines()) == 1 and 'Traceback' not in output, output
    assert output.startswith('[ERROR] [ticker]: start-up error: ') and reason in output
    assert str(path) in output


def test_worker_takes_the_newest_counts_the_superseded_and_survives_errors():
    from vgm_common.worker import Worker

    release, done, errors, taken = threading.Event(), threading.Event(), [], []

    def process(item):
        release.wait(10.0)
        if item == 'bad':
            raise ValueError('bad item')
        taken.append(item)
        if item == 'last':
            done.set()

    dropped = []
    worker = Worker(process, errors.append, 'probe', on_drop=dropped.append)
    worker.submit('first')  # being processed while the next three arrive
    wait_for(lambda: not worker._waiting, 10.0, "'first' taken by the thread", interval=0.01)
    for item in ('a', 'b', 'bad'):
        worker.submit(item)
    release.set()
    wait_for(lambda: errors, 10.0, 'the error of the bad item', interval=0.01)
    worker.submit('last')  # still serving after the error
    assert done.wait(10.0)
    worker.close()
    assert taken == ['first', 'last'] and worker.dropped == 2 and dropped == ['a', 'b']
    assert [str(e) for e in errors] == ['bad item']


def test_worker_keeping_the_oldest_refuses_when_full_and_idle_work_yields():
    from vgm_common.worker import Worker

    release, taken = threading.Event(), []

    def process(item):
        release.wait(10.0)
        taken.append(item)

    worker = Worker(process, lambda error: None, 'probe', capacity=2, keep='oldest')
    assert worker.submit('first')
    wait_for(lambda: not worker._waiting, 10.0, "'first' taken by the thread", interval=0.01)
    assert worker.submit_if_idle('tidy up')  # nothing waits: queued
    assert not worker.submit_if_idle('tidy up again')  # something waits: not needed
    assert worker.submit('second') and not worker.submit('third')  # full: refused
    release.set()
    wait_for(lambda: len(taken) == 3, 10.0, 'three items processed', interval=0.01)
    worker.close()
    assert taken == ['first', 'tidy up', 'second'] and worker.dropped == 1
    with pytest.raises(ValueError, match='keep'):
        Worker(process, lambda error: None, 'probe', keep='random')


def test_worker_survives_a_failing_error_report(capfd):
    from vgm_common.worker import Worker

    done = threading.Event()

    def process(item):
        if item == 'bad':
            raise ValueError('bad item')
        done.set()

    def broken_report(error):
        raise RuntimeError('the report failed too')

    worker = Worker(process, broken_report, 'probe')
    worker.submit('bad')
    wait_for(
        lambda: 'the report failed too' in capfd.readouterr().err,
        10.0,
        'the failing report printed',
        interval=0.01,
    )
    worker.submit('good')  # still serving
    assert done.wait(10.0)
    worker.close()
