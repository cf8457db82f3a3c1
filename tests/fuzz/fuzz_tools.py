"""The fuzz suite's driver: one node process under test, a probe node in the test process.

Each case sends something bad (a message, a parameter change, a service call out of
order) and then checks the node: the process is alive, it answers ``get_parameters``
within ``ANSWER_TIMEOUT``, and, for input that must be refused, it said so: a
``rejected ...`` diagnostic whose count grew, or a new WARN/ERROR line in its log."""

import re
import time
from dataclasses import dataclass, field

import psutil
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters
from std_srvs.srv import Trigger

from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import DIAGNOSTICS_TOPIC

ANSWER_TIMEOUT = 10.0  # [s] get_parameters on a loaded 2-core machine
REJECTION_TIMEOUT = 15.0  # [s] for the node to report a refused input
# Declared by rclpy itself (get_parameters answers nothing for the second).
_RCLPY_PARAMETERS = ('use_sim_time', 'start_type_description_service')
_LOG_PROBLEM = re.compile(r'\[(WARN|ERROR)\]')
_TYPE_NAMES = {
    ParameterType.PARAMETER_BOOL: 'bool',
    ParameterType.PARAMETER_INTEGER: 'int',
    ParameterType.PARAMETER_DOUBLE: 'float',
    ParameterType.PARAMETER_STRING: 'str',
    ParameterType.PARAMETER_DOUBLE_ARRAY: 'float[]',
    ParameterType.PARAMETER_INTEGER_ARRAY: 'int[]',
    ParameterType.PARAMETER_STRING_ARRAY: 'str[]',
    ParameterType.PARAMETER_BOOL_ARRAY: 'bool[]',
}


@dataclass
class DeclaredParameter:
    name: str
    type: str
    value: object
    read_only: bool
    description: str
    range: tuple = None  # (min, max) from the descriptor
    choices: list = field(default_factory=list)


class Fuzzer:
    """Drives ``process`` (a harness.NodeProcess running node ``node_name``) from the
    test's ``probe`` node (conftest's rclpy_node). ``cases`` counts what was tried."""

    def __init__(self, probe, process, node_name):
        self.probe = probe
        self.process = process
        self.node_name = node_name
        self.cases = []
        self.outcomes = {}  # case -> 'refused' | 'survived' | 'parameter refused'
        self._publishers = {}
        self._rejected = {}  # diagnostic status name -> highest count seen
        self._problems = 0  # WARN/ERROR diagnostics of this node seen
        probe.create_subscription(
            DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics, DEFAULT_QOS
        )

    # -- observing the node ---------------------------------------------------------

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if not status.name.startswith(f'{self.node_name}: '):
                continue
            if status.level in (DiagnosticStatus.WARN, DiagnosticStatus.ERROR):
                self._problems += 1
            if 'rejected' in status.name:
                count = next((int(v.value) for v in status.values if v.key == 'count'), 1)
                self._rejected[status.name] = max(self._rejected.get(status.name, 0), count)

    def _log_problems(self):
        return len(_LOG_PROBLEM.findall(self.process.output()))

    def _said_something(self, before):
        rejected, problems, log = before
        grown = any(count > rejected.get(name, 0) for name, count in self._rejected.items())
        return grown or self._problems > problems or self._log_problems() > log

    def _snapshot(self):
        return dict(self._rejected), self._problems, self._log_problems()

    def wait_until_serving(self, timeout=60.0):
        """Until the node answers get_parameters (bounded by ``timeout``). A new client
        is "ready" once its requests reach the node, but the node's answer can still go
        out before the client's response reader is discovered, and be lost ("failed to
        send response (timeout)" in the node's log, seen once in a full run): at start-up
        such a lost answer is asked for again; later, check_serving allows none."""
        deadline = time.monotonic() + timeout
        request = GetParameters.Request(names=['use_sim_time'])
        while True:
            try:
                self.call(GetParameters, f'/{self.node_name}/get_parameters', request, 5.0)
                return
            except TimeoutError:
                if time.monotonic() > deadline:
                    raise AssertionError(
                        f'{self.node_name} does not answer get_parameters within {timeout} s'
                    ) from None

    def check_serving(self, case):
        """Alive and answering get_parameters, else AssertionError naming ``case``."""
        assert self.process.alive(), (
            f'{self.node_name} died after {case!r}:\n{self.process.output()[-3000:]}'
        )
        request = GetParameters.Request(names=['use_sim_time'])
        try:
            self.call(GetParameters, f'/{self.node_name}/get_parameters', request, ANSWER_TIMEOUT)
        except TimeoutError:
            raise AssertionError(
                f'{self.node_name} stopped answering get_parameters after {case!r}'
            ) from None

    def rss_bytes(self):
        return sum(
            p.memory_info().rss
            for p in [psutil.Process(self.process.proc.pid)]
            + psutil.Process(self.process.proc.pid).children(recursive=True)
        )

    # -- acting ---------------------------------------------------------------------

    def publisher(self, topic, msg_type, qos=DEFAULT_QOS):
        key = (topic, msg_type, qos.durability)
        if key not in self._publishers:
            publisher = self.probe.create_publisher(msg_type, topic, qos)
            self.probe.spin_until(
                lambda: publisher.get_subscription_count() > 0,
                30,
                f'{self.node_name} to subscribe to {topic}',
            )
            self._publishers[key] = publisher
        return self._publishers[key]

    def call(self, srv_type, name, request, timeout):
        """The answer of service ``name``; AssertionError if the node died meanwhile."""
        answer = self.probe.graph.call(
            name,
            timeout,
            srv_type=srv_type,
            request=request,
            give_up=lambda: not self.process.alive(),
        )
        assert self.process.alive(), (
            f'{self.node_name} died serving {name}:\n{self.process.output()[-3000:]}'
        )
        return answer

    def reject(self, case, send):
        """``send()`` something the node must refuse: it says so and keeps serving."""
        self.cases.append(case)
        before = self._snapshot()
        send()
        try:
            self.probe.spin_until(
                lambda: self._said_something(before) or not self.process.alive(),
                REJECTION_TIMEOUT,
                f'{self.node_name} to report {case!r}',
            )
        except TimeoutError:
            raise AssertionError(
                f'{self.node_name} accepted {case!r} silently (no rejected diagnostic, no warning)'
            ) from None
        self.check_serving(case)
        self.outcomes[case] = 'refused'

    def survive(self, case, send):
        """``send()`` something unusual but not wrong: the node keeps serving."""
        self.cases.append(case)
        send()
        self.check_serving(case)
        self.outcomes[case] = 'survived'

    # -- parameters -----------------------------------------------------------------

    def parameters(self):
        """The node's declared parameters with descriptors and values."""
        names = self.call(
            ListParameters,
            f'/{self.node_name}/list_parameters',
            ListParameters.Request(),
            ANSWER_TIMEOUT,
        ).result.names
        names = [
            n for n in names if n not in _RCLPY_PARAMETERS and not n.startswith('qos_overrides')
        ]
        descriptors = self.call(
            DescribeParameters,
            f'/{self.node_name}/describe_parameters',
            DescribeParameters.Request(names=names),
            ANSWER_TIMEOUT,
        ).descriptors
        values = self.call(
            GetParameters,
            f'/{self.node_name}/get_parameters',
            GetParameters.Request(names=names),
            ANSWER_TIMEOUT,
        ).values
        assert len(values) == len(names), f'get_parameters answered {len(values)} of {names}'
        declared = []
        for name, descriptor, value in zip(names, descriptors, values):
            kind = _TYPE_NAMES.get(value.type)
            if kind is None:
                continue
            parameter = DeclaredParameter(
                name, kind, _python_value(value), descriptor.read_only, descriptor.description
            )
            if descriptor.integer_range:
                r = descriptor.integer_range[0]
                parameter.range = (r.from_value, r.to_value)
            elif descriptor.floating_point_range:
                r = descriptor.floating_point_range[0]
                parameter.range = (r.from_value, r.to_value)
            choices = re.search(r'One of: (.*)\.$', descriptor.description)
            if choices:
                parameter.choices = [c.strip() for c in choices.group(1).split(',')]
            declared.append(parameter)
        return declared

    def set_parameter(self, name, value):
        """(successful, reason) of setting ``name`` to ``value`` over the service."""
        request = SetParameters.Request(
            parameters=[ParameterMsg(name=name, value=_parameter_value(value))]
        )
        result = self.call(
            SetParameters, f'/{self.node_name}/set_parameters', request, ANSWER_TIMEOUT
        ).results[0]
        return result.successful, result.reason

    def refuse_parameter(self, case, name, value):
        """Setting ``name`` to ``value`` is refused with a reason; the node serves on."""
        self.cases.append(case)
        successful, reason = self.set_parameter(name, value)
        assert not successful and reason, f'{self.node_name} accepted {case!r}'
        self.check_serving(case)
        self.outcomes[case] = 'parameter refused'

    def summary(self):
        """One line: the kinds tried and how each ended (what the README's table shows)."""
        kinds = set(self.cases)
        counts = {
            outcome: sum(1 for o in self.outcomes.values() if o == outcome)
            for outcome in ('refused', 'parameter refused', 'survived')
        }
        other = len(kinds - set(self.outcomes))
        return (
            f'fuzz summary {self.node_name}: {len(kinds)} kinds, '
            f'{counts["refused"]} refused with a report, '
            f'{counts["parameter refused"]} parameter changes refused with a reason, '
            f'{counts["survived"]} survived, {other} served or answered'
        )

    def trigger(self, name, timeout=30.0):
        return self.call(Trigger, f'/{self.node_name}/{name}', Trigger.Request(), timeout)


def _python_value(value):
    return {
        ParameterType.PARAMETER_BOOL: value.bool_value,
        ParameterType.PARAMETER_INTEGER: value.integer_value,
        ParameterType.PARAMETER_DOUBLE: value.double_value,
        ParameterType.PARAMETER_STRING: value.string_value,
        ParameterType.PARAMETER_DOUBLE_ARRAY: list(value.double_array_value),
        ParameterType.PARAMETER_INTEGER_ARRAY: list(value.integer_array_value),
        ParameterType.PARAMETER_STRING_ARRAY: list(value.string_array_value),
        ParameterType.PARAMETER_BOOL_ARRAY: list(value.bool_array_value),
    }[value.type]


def _parameter_value(value):
    if isinstance(value, bool):
        return ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
    if isinstance(value, int):
        return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
    if isinstance(value, float):
        return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
    if isinstance(value, str):
        return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
    if isinstance(value, list) and all(isinstance(v, str) for v in value) and value:
        return ParameterValue(type=ParameterType.PARAMETER_STRING_ARRAY, string_array_value=value)
    if isinstance(value, list):
        return ParameterValue(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=[float(v) for v in value]
        )
    raise TypeError(f'no parameter type for {value!r}')


def fuzz_parameters(fuzzer):
    """Every settable parameter: values of the wrong kind, NaN, beyond its range and
    outside its choices are refused with a reason; its range's ends and every choice are
    taken or refused with a reason (cross-checks), never a crash; then the start value is
    restored. Returns the parameters seen."""
    declared = fuzzer.parameters()
    for p in declared:
        if p.read_only:
            fuzzer.refuse_parameter(f'set read-only {p.name}', p.name, p.value)
            continue
        wrong = {
            'bool': 'yes',
            'int': 'many',
            'float': 'fast',
            'str': 3.5,
            'float[]': 'a list',
            'int[]': 'a list',
            'str[]': 1.0,
            'bool[]': 2.0,
        }[p.type]
        fuzzer.refuse_parameter(f'{p.name} := {wrong!r}', p.name, wrong)
        if p.type == 'float':
            fuzzer.refuse_parameter(f'{p.name} := nan', p.name, float('nan'))
            fuzzer.refuse_parameter(f'{p.name} := inf', p.name, float('inf'))
        if p.type == 'float[]' and p.value:
            fuzzer.refuse_parameter(
                f'{p.name} := [nan, ...]', p.name, [float('nan')] * len(p.value)
            )
        trials = []
        if p.range:
            low, high = p.range
            step = 1 if p.type == 'int' else max(1.0, abs(high - low)) * 1e-3
            fuzzer.refuse_parameter(f'{p.name} := above its range', p.name, _kind(p, high + step))
            fuzzer.refuse_parameter(f'{p.name} := below its range', p.name, _kind(p, low - step))
            trials = [_kind(p, low), _kind(p, high)]
        if p.choices:
            fuzzer.refuse_parameter(f'{p.name} := no choice', p.name, 'no-such-choice')
            trials = [c for c in p.choices if c != p.value]
        if p.type == 'bool':
            trials = [not p.value]
        for value in trials:
            fuzzer.cases.append(f'{p.name} := {value!r} (in range)')
            successful, reason = fuzzer.set_parameter(p.name, value)
            assert successful or reason, f'{p.name} := {value!r} refused without a reason'
            fuzzer.check_serving(f'{p.name} := {value!r}')
            successful, reason = fuzzer.set_parameter(p.name, p.value)
            assert successful, f'{p.name} could not be set back to {p.value!r}: {reason}'
    return declared


def _kind(parameter, value):
    return int(value) if parameter.type == 'int' else float(value)


def wait_gone(process, timeout=30.0):
    deadline = time.monotonic() + timeout
    while process.alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    return not process.alive()
