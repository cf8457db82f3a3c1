"""What every node does at its edges: typed parameters with descriptors and validation,
diagnostics on /diagnostics, throttled rejection of bad input, and a clean ``main``."""

from __future__ import annotations

import array
import contextlib
import dataclasses
import difflib
import functools
import math
import os
import re
import signal
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import (
    Callable,
    Coroutine,
    Iterable,
    Iterator,
    Mapping,
    MutableMapping,
    Sequence,
)
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType, MappingProxyType
from typing import TYPE_CHECKING, Any, ClassVar, Generic, NoReturn, TypeVar

import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy._rclpy_pybind11 import RCLError
from rclpy.duration import Duration
from rclpy.exceptions import (
    InvalidHandle,
    InvalidParameterTypeException,
    InvalidParameterValueException,
)
from rclpy.executors import (
    Executor,
    ExternalShutdownException,
    MultiThreadedExecutor,
    SingleThreadedExecutor,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.signals import SignalHandlerOptions

from vgm_common.errors import VgmError
from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import DIAGNOSTICS_TOPIC

if TYPE_CHECKING:
    from rclpy.service import Service


class ParameterError(VgmError):
    """A parameter has a value of the wrong kind or out of range."""


@dataclass
class Param:
    """One declared parameter: ``default`` fixes its kind (bool, int, float, str, list; a
    list's elements are of the kind of the default's first element, if it has one)."""

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None  # (min, max) for numbers, inclusive
    choices: Sequence[str] | None = None
    check: Callable[[Any], str | None] | None = None  # returns a reason if bad
    read_only: bool = False
    kind: type = field(init=False)

    def __post_init__(self) -> None:
        self.kind = type(self.default)

    def _error(self, reason: str, value: Any) -> ParameterError:
        return ParameterError(f'parameter {self.name!r}: {reason}', key=self.name, value=value)

    def coerce(self, value: Any) -> Any:
        """The value in this parameter's kind, or ParameterError with a reason."""
        if self.kind is float and _is_kind(value, int):
            value = float(value)  # `rate:=100` for a float parameter is what users type
        if self.kind is list:
            value = self._coerce_list(value)
        elif not _is_kind(value, self.kind):
            raise self._error(f'expected {self.kind.__name__}, got {value!r}', value)
        if self.kind is float and not math.isfinite(value):
            raise self._error(f'must be finite, got {value}', value)
        if self.range and not self.range[0] <= value <= self.range[1]:
            raise self._error(f'{value} is outside [{self.range[0]}, {self.range[1]}]', value)
        if self.choices and value not in self.choices:
            raise self._error(f'{value!r} is not one of {", ".join(self.choices)}', value)
        reason = self.check(value) if self.check else None
        if reason:
            raise self._error(reason, value)
        return value

    def _coerce_list(self, value: Any) -> list[Any]:
        if isinstance(value, array.array):  # how rclpy hands a numeric array at run time
            value = value.tolist()
        if not isinstance(value, (list, tuple)):
            raise self._error(f'expected a list, got {value!r}', value)
        value = list(value)
        if self.default:
            element = type(self.default[0])
            if element is float:
                value = [float(v) if _is_kind(v, int) else v for v in value]
            if not all(_is_kind(v, element) for v in value):
                raise self._error(f'expected a list of {element.__name__}, got {value!r}', value)
        return value

    def descriptor(self) -> ParameterDescriptor:
        """The ParameterDescriptor to declare it with: the description (plus the choices),
        read-only (except an empty-list default, declared unset) and, for a number, its
        range. Typing is dynamic, so that ``coerce`` reports a wrong kind in one line."""
        text = self.description + (f' One of: {", ".join(self.choices)}.' if self.choices else '')
        # Dynamic typing lets coerce() give the one-line error (and accept an integer
        # for a float) instead of rclpy raising a traceback at declaration.
        # An empty list is declared typed but unset and then set (NodeParameters), which
        # rclpy refuses for a read-only one: its read-only-ness is then ours to enforce.
        descriptor = ParameterDescriptor(
            description=text,
            read_only=self.read_only and self.default != [],
            dynamic_typing=self.default != [],
        )
        if self.range and self.kind is int:
            descriptor.integer_range = [
                IntegerRange(from_value=self.range[0], to_value=self.range[1])
            ]
        elif self.range and self.kind is float:  # `ros2 param describe` shows it
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(self.range[0]), to_value=float(self.range[1]))
            ]
        return descriptor


class NodeParameters:
    """Declares ``params`` on ``node``, validates start-up values (raising
    ParameterError naming the parameter) and later changes (refused with a reason, and
    reported as rejected input to ``diagnostics`` if given). Current values are
    attributes: ``self.params.rate``; ``on_change[name]``, if given, is called with a
    parameter's new value once a change is set. A value given for a name the node does
    not declare is a ParameterError naming the new name if ``renamed`` (old -> new) has
    it, else a warning. Values that must go together (a minimum below its maximum, one
    weight per joint) are checked by ``add_check``."""

    def __init__(
        self,
        node: Node,
        params: Sequence[Param],
        diagnostics: Diagnostics | None = None,
        on_change: Mapping[str, Callable[[Any], None]] | None = None,
        renamed: Mapping[str, str] | None = None,
    ) -> None:
        self._node = node
        self._params = {p.name: p for p in params}
        self._diagnostics = diagnostics
        self._on_change = dict(on_change or {})
        unknown = set(self._on_change) - set(self._params)
        if unknown:  # a programming error: the hook would never run
            raise ValueError(f'on_change names undeclared parameters: {sorted(unknown)}')
        values: dict[str, Any] = {}
        for p in params:
            # rclpy cannot infer an array type from an empty default.
            default = Parameter.Type.STRING_ARRAY if p.default == [] else p.default
            try:
                value = node.declare_parameter(p.name, default, p.descriptor()).value
            except (InvalidParameterTypeException, InvalidParameterValueException) as error:
                # A value of the wrong type, or outside a range the descriptor states.
                raise ParameterError(f'parameter {p.name!r}: {error}', key=p.name) from None
            if value is None and p.default == []:
                # Typed but unset, rclpy's get_parameters service would answer nothing
                # for it (nor for any name asked with it): set the empty list.
                node.set_parameters([Parameter(p.name, Parameter.Type.STRING_ARRAY, [])])
            values[p.name] = _coerce(p, value)
        self._values = values
        self._check_given_names(renamed or {})
        self._checks: list[Callable[[Mapping[str, Any]], str | None]] = []
        node.add_on_set_parameters_callback(self._on_set)
        node.add_post_set_parameters_callback(self._on_changed)

    def _check_given_names(self, renamed: Mapping[str, str]) -> None:
        # rclpy drops a value given for an undeclared name without a word: a typo, or a
        # name from before a rename, would silently leave the default in force. rclpy
        # has no public accessor for what was given.
        if not set(renamed.values()) <= set(self._params):  # a programming error
            raise ValueError(f'renamed to undeclared parameters: {dict(renamed)}')
        given = getattr(self._node, '_parameter_overrides', {})
        unknown = sorted(n for n in given if not self._node.has_parameter(n))
        moved = [old for old in unknown if old in renamed]
        if moved:
            renames = '; '.join(f'{old!r} is now {renamed[old]!r}' for old in moved)
            raise ParameterError(f'renamed parameters (CHANGELOG.md): {renames}', key=moved[0])
        if unknown:
            self._node.get_logger().warning(
                'ignored, not parameters of this node: '
                + ', '.join(_with_suggestion(name, self._params) for name in unknown)
            )

    def __getattr__(self, name: str) -> Any:
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(name) from None

    @property
    def values(self) -> Mapping[str, Any]:
        """The current values, name -> value (read-only)."""
        return MappingProxyType(self._values)

    @property
    def declared(self) -> Mapping[str, Param]:
        """The declared parameters, name -> Param (read-only)."""
        return MappingProxyType(self._params)

    def add_check(self, check: Callable[[Mapping[str, Any]], str | None]) -> None:
        """``check(values)`` (name -> value) returns a reason if the values do not go
        together. It is run now, raising ParameterError (a start-up error), and on every
        change, which it refuses with the reason."""
        reason = check(self._values)
        if reason:
            raise ParameterError(f'parameters: {reason}')
        self._checks.append(check)

    def _on_set(self, parameters: list[Parameter]) -> SetParametersResult:
        proposed = dict(self._values)
        try:
            for parameter in parameters:
                spec = self._params.get(parameter.name)
                if spec is None:
                    continue
                if spec.read_only:
                    return SetParametersResult(
                        successful=False, reason=f'{spec.name} is read-only'
                    )
                proposed[spec.name] = _coerce(spec, parameter.value)
            reasons = [reason for check in self._checks if (reason := check(proposed))]
            if reasons:
                raise ParameterError(f'parameters: {"; ".join(reasons)}')
        except ParameterError as error:
            if self._diagnostics is not None:
                self._diagnostics.reject('parameter change', error)
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _on_changed(self, parameters: list[Parameter]) -> None:
        # After every set-parameters callback accepted the change: only now is it real.
        for parameter in parameters:
            spec = self._params.get(parameter.name)
            if spec is None:
                continue
            value = self._values[spec.name] = _coerce(spec, parameter.value)
            if spec.name in self._on_change:
                self._on_change[spec.name](value)


class TopicTypeError(VgmError):
    """A topic the node would publish or subscribe already carries another type."""


def message_type_name(msg_type: Any) -> str:
    """'sensor_msgs/msg/Image' for the Python class of a ROS message."""
    package, interface = msg_type.__module__.split('.')[:2]
    return f'{package}/{interface}/{msg_type.__name__}'


TYPE_CHECK_PERIOD = 2.0  # [s] how often a node looks for other types on its topics


def _with_suggestion(name: str, declared: Iterable[str]) -> str:
    """``name``, with the nearest declared name if one is near: 'rat (did you mean rate?)'."""
    near = difflib.get_close_matches(name, list(declared), n=1, cutoff=0.75)
    return f'{name} (did you mean {near[0]}?)' if near else name


def params_file_section_warnings(
    path: str | Path, node_name: str, declared: Callable[[str], bool]
) -> list[str]:
    """What a ``--params-file`` holds for the node of fully qualified name ``node_name``
    that a user would want to hear about, as warning texts: no section applies to it (rcl
    then starts it on its defaults without a word), or the sections that apply (its own,
    ``/**``, ...) hold no name ``declared`` says is its parameter."""
    content = yaml.safe_load(Path(path).read_text())
    if not isinstance(content, dict):
        return []  # check_params_files refused it already
    sections = [str(key) for key in content]
    found = ', '.join(sections) or 'none'
    matching = [key for key in sections if _section_matches(key, node_name)]
    if not matching:
        return [
            f'params file {path} has no section for {node_name} (its sections: {found}): '
            'none of its values apply to this node'
        ]
    names = [
        name
        for key in matching
        for name in _dotted_names((content[key] or {}).get('ros__parameters') or {})
    ]
    if names and not any(declared(name) for name in names):
        return [
            f'params file {path}: its section {", ".join(matching)} holds no parameter '
            f'of {node_name} (its sections: {found})'
        ]
    return []


def _section_matches(section: str, node_name: str) -> bool:
    """Whether the params file section ``section`` applies to ``node_name`` as rcl reads
    it: a name without a namespace is in /, ``/**`` any namespaces, ``*`` one token."""
    key = section if section.startswith('/') else f'/{section}'
    pattern = re.escape(key).replace(r'/\*\*', '(?:/[^/]+)*').replace(r'\*', '[^/]*')
    return re.fullmatch(pattern, node_name) is not None


def _dotted_names(values: Mapping[str, Any], prefix: str = '') -> list[str]:
    """Parameter names of a ``ros__parameters`` mapping: nested mappings are dotted."""
    names = []
    for key, value in values.items():
        if isinstance(value, dict):
            names += _dotted_names(value, f'{prefix}{key}.')
        else:
            names.append(f'{prefix}{key}')
    return names


def _params_files(argv: Sequence[str]) -> list[str]:
    return [path for flag, path in zip(argv, argv[1:]) if flag == '--params-file']


class GraphNode(Node):
    """What every node of the graph starts with: a Node named by the class's
    ``node_name``, its ``diagnostics`` (on /diagnostics) and its ``params``
    (NodeParameters of ``parameters``, a refused change reported to the diagnostics;
    ``on_change`` as there, ``renamed_parameters`` its ``renamed``).

    A publisher or subscription on a topic that already carries another type (a remap
    such as ``-r /tool/pressure:=/joint_states``) is a TopicTypeError naming both types
    (a start-up error); a typed subscription whose topic gets a publisher of another
    type later is one error line and diagnostic naming both, every TYPE_CHECK_PERIOD."""

    node_name: ClassVar[str]
    renamed_parameters: ClassVar[Mapping[str, str]] = {}

    def __init__(
        self,
        parameters: Sequence[Param],
        on_change: Mapping[str, Callable[[Any], None]] | None = None,
        **kwargs: Any,
    ) -> None:
        # Node.__init__ already creates publishers through create_publisher.
        self._own_types: dict[str, str] = {}  # resolved topic -> its type in this node
        self._typed_subscriptions: dict[str, tuple[str, str]] = {}  # -> (type, name given)
        self._reported_types: set[tuple[str, str]] = set()  # (topic, other type) logged
        super().__init__(self.node_name, **kwargs)
        self.diagnostics = Diagnostics(self)
        self.params = NodeParameters(
            self, parameters, self.diagnostics, on_change, self.renamed_parameters
        )
        self.create_timer(TYPE_CHECK_PERIOD, self._check_topic_types)

    def create_publisher(self, msg_type: Any, topic: str, *args: Any, **kwargs: Any) -> Any:
        """Node.create_publisher, refusing a topic that carries another type in this node
        (rcl would fail with 'invalid allocator')."""
        self._claim_topic(msg_type, topic, foreign_too=False)
        return super().create_publisher(msg_type, topic, *args, **kwargs)

    def create_subscription(
        self,
        msg_type: Any,
        topic: str,
        callback: Callable[[Any], None],  # as rclpy annotates it
        *args: Any,
        **kwargs: Any,
    ) -> Any:
        """Node.create_subscription, refusing a topic known to carry another type (DDS
        would deliver nothing, or rcl fail with 'invalid allocator'); a raw subscription
        (of whatever type a topic has: recorder, live_view) is not checked later."""
        resolved = self._claim_topic(msg_type, topic, foreign_too=not kwargs.get('raw'))
        if not kwargs.get('raw'):
            self._typed_subscriptions[resolved] = (message_type_name(msg_type), topic)
        return super().create_subscription(msg_type, topic, callback, *args, **kwargs)

    def _claim_topic(self, msg_type: Any, topic: str, foreign_too: bool) -> str:
        resolved = self.resolve_topic_name(topic)
        ours = message_type_name(msg_type)
        others = {self._own_types.get(resolved, ours)} - {ours}
        if foreign_too:
            others |= set(dict(self.get_topic_names_and_types()).get(resolved, ())) - {ours}
        if others:
            raise TopicTypeError(
                f'{self._topic_as_given(topic)} carries {", ".join(sorted(others))}; '
                f'this node needs {ours} there',
                key=resolved,
                value=sorted(others),
            )
        self._own_types.setdefault(resolved, ours)
        return resolved

    def _topic_as_given(self, topic: str) -> str:
        """'/tool/pressure (remapped to /joint_states)', or the topic if not remapped."""
        expanded = self.resolve_topic_name(topic, only_expand=True)
        resolved = self.resolve_topic_name(topic)
        return resolved if expanded == resolved else f'{expanded} (remapped to {resolved})'

    def _check_topic_types(self) -> None:
        """One error line and diagnostic per other type seen on a typed subscription's
        topic: its messages never arrive, and without a word the node would just wait."""
        types = dict(self.get_topic_names_and_types())
        for resolved, (ours, given) in self._typed_subscriptions.items():
            for other in sorted(set(types.get(resolved, ())) - {ours}):
                if (resolved, other) in self._reported_types:
                    continue
                self._reported_types.add((resolved, other))
                message = (
                    f'{self._topic_as_given(given)} carries {other}; this node '
                    f'subscribes it as {ours} and receives none of those'
                )
                self.get_logger().error(message)
                self.diagnostics.publish(
                    'topic type', 'error', message, {'topic': resolved, 'type': other}
                )


Config = TypeVar('Config')


@dataclass(frozen=True)
class ConfigParams(Generic[Config]):
    """How a core's settings (a dataclass or NamedTuple with a default for every field)
    are filled from a node's parameters: a field takes the parameter of its own name, or
    ``renamed[field]``; a field no parameter names keeps the core's default. The core's
    defaults are the parameters' defaults (``Param('speed', TRACKING.defaults.speed,
    ...)``), and a test checks each node's declared defaults against them."""

    config_type: Callable[..., Config]
    renamed: Mapping[str, str] = field(default_factory=dict)

    @property
    def defaults(self) -> Config:
        """The core's settings with every field at its default."""
        return self.config_type()

    def field_defaults(self) -> dict[str, Any]:
        """Field name -> the core's default, in the fields' order."""
        defaults: Any = self.defaults
        if dataclasses.is_dataclass(defaults):
            return {f.name: getattr(defaults, f.name) for f in dataclasses.fields(defaults)}
        return dict(defaults._asdict())  # a NamedTuple

    def param_names(self, declared: Iterable[str]) -> dict[str, str]:
        """Field -> parameter, for the fields whose parameter is in ``declared``. A
        ``renamed`` entry naming no field or no declared parameter is a programming
        error (the parameter would silently do nothing): ValueError."""
        declared = set(declared)
        fields = self.field_defaults()
        wrong = [
            f'{f} -> {p}' for f, p in self.renamed.items() if f not in fields or p not in declared
        ]
        if wrong:
            raise ValueError(f'{self.config_type.__name__}: no such field or parameter: {wrong}')
        names = {f: self.renamed.get(f, f) for f in fields}
        return {f: p for f, p in names.items() if p in declared}

    def fields(self, params: NodeParameters) -> dict[str, Any]:
        """Field -> the current value of its parameter, for the fields that have one (a
        list where the core's default is a tuple becomes a tuple)."""
        defaults = self.field_defaults()
        return {
            f: tuple(params.values[p]) if isinstance(defaults[f], tuple) else params.values[p]
            for f, p in self.param_names(params.declared).items()
        }

    def build(self, params: NodeParameters) -> Config:
        """The core's settings from the parameters' current values."""
        return self.config_type(**self.fields(params))


def _coerce(spec: Param, value: Any) -> Any:
    # An empty list given on the command line (`topics:=[]`) arrives unset.
    return spec.coerce([] if value is None and spec.kind is list else value)


def _is_kind(value: object, kind: type) -> bool:
    """``isinstance``, except that a bool is no int (ROS keeps them apart)."""
    return isinstance(value, kind) and not (kind is int and isinstance(value, bool))


class CountingPublisher(Publisher):
    """A publisher that counts what it sent. Pass ``publisher_class=CountingPublisher`` to
    ``create_publisher``; ``run_node`` logs the counts when the node stops (``published:
    /topic=N ...``, read back by ``parse_published_counts``), so a recording can be
    checked for lost messages."""

    sent = 0

    def publish(self, msg: Any) -> None:
        """Publish ``msg`` and count it in ``sent``."""
        super().publish(msg)
        self.sent += 1


def subscriber_gate_params(what: str) -> list[Param]:
    """The three parameters of a SubscriberGate: ``min_subscribers`` (0 = open at once),
    ``wait_for_nodes`` and ``subscriber_timeout``; ``what`` says what waits and on which
    topics the count applies, e.g. 'Publish only once every camera topic has'."""
    return [
        Param(
            'min_subscribers',
            0,
            f'{what} this many matched subscribers, at most '
            'subscriber_timeout: a reliable publisher drops what it sends before '
            'discovery. 0 = start at once.',
            range=(0, 100),
            read_only=True,
        ),
        Param(
            'wait_for_nodes',
            [],
            'Also wait until each of these nodes (a name, or '
            '/namespace/name) has a matched subscription on every topic the node '
            'publishes, e.g. [recorder]: a count alone is met by other subscribers '
            'while the recorder is still starting. Name only nodes that subscribe '
            'every stream from their start, never one that subscribes on demand '
            '(live_view, while a viewer watches): without its viewer the wait lasts '
            'subscriber_timeout.',
            check=_node_names,
            read_only=True,
        ),
        Param(
            'subscriber_timeout',
            30.0,
            '[s] Longest wait for min_subscribers and wait_for_nodes.',
            range=(0.0, 3600.0),
            read_only=True,
        ),
    ]


def _node_names(names: Iterable[object]) -> str | None:
    """A reason if ``names`` holds anything but non-empty strings, else None."""
    bad = [name for name in names if not isinstance(name, str) or not name]
    return f'must hold node names, got {bad}' if bad else None


def _full_node_name(namespace: str, name: str) -> str:
    return f'{namespace.rstrip("/")}/{name}'


class SubscriberGate:
    """Holds streams back until their subscribers are there, or ``timeout`` [s] passed
    since its creation: a reliable publisher drops what it sends before discovery has
    matched a reader, so a recorder started alongside would miss a stream's first
    messages. Thread-safe; ``opened`` is set once open.

    Open when each of ``counted`` (default: all ``publishers``) has ``min_subscribers``
    matched subscribers, and each node of ``wait_for_nodes`` has subscribed to every one
    of ``publishers`` with every discovered subscription matched (the graph lists a
    subscription when it is discovered, the count says when it is matched)."""

    def __init__(
        self,
        node: Node,
        publishers: Iterable[Publisher],
        min_subscribers: int,
        timeout: float,
        wait_for_nodes: Iterable[str] = (),
        counted: Iterable[Publisher] | None = None,
    ) -> None:
        self._node, self._publishers = node, tuple(publishers)
        self._counted = self._publishers if counted is None else tuple(counted)
        self._min_subscribers, self._timeout = min_subscribers, timeout
        self._wait_for_nodes = tuple(wait_for_nodes)
        self._created = time.monotonic()
        self.opened = threading.Event()

    def missing(self) -> list[str]:
        """What the gate still waits for, as 'node on topic' / 'N of M on topic' texts."""
        missing = [
            f'{p.get_subscription_count()} of {self._min_subscribers} subscribers '
            f'on {p.topic_name}'
            for p in self._counted
            if p.get_subscription_count() < self._min_subscribers
        ]
        if not self._wait_for_nodes:
            return missing
        for publisher in self._publishers:
            infos = self._node.get_subscriptions_info_by_topic(publisher.topic_name)
            names = {info.node_name for info in infos} | {
                _full_node_name(info.node_namespace, info.node_name) for info in infos
            }
            missing += [
                f'{name} on {publisher.topic_name}'
                for name in self._wait_for_nodes
                if name not in names
            ]
            if publisher.get_subscription_count() < len(infos):
                missing.append(f'matching on {publisher.topic_name}')
        return missing

    def is_open(self) -> bool:
        """True once the gate is open: the subscribers are there or the timeout passed.
        Opening logs how long it waited (a warning naming what is missing after a
        timeout) and sets ``opened``; the gate then stays open."""
        if self.opened.is_set():
            return True
        missing = self.missing()
        waited = time.monotonic() - self._created
        if missing and waited <= self._timeout:
            return False
        if missing:
            self._node.get_logger().warning(
                f'publishing after {waited:.1f} s without: {"; ".join(missing)}'
            )
        elif self._min_subscribers or self._wait_for_nodes:
            self._node.get_logger().info(f'subscribers matched after {waited:.1f} s')
        self.opened.set()
        return True


def parse_published_counts(log_text: str) -> dict[str, int]:
    """{topic: messages published} from a node's 'published: /topic=N ...' log lines (a
    node may log several; a topic counted in several lines keeps the last count)."""
    lines = re.findall(r'published: (.*)', log_text)
    if not lines:
        raise ValueError('no "published:" line in the log')
    return {topic: int(n) for line in lines for topic, n in re.findall(r'(\S+)=(\d+)', line)}


def _log_published_counts(node: Node) -> None:
    counts: dict[str, int] = {}
    for publisher in node.publishers:
        if isinstance(publisher, CountingPublisher):
            counts[publisher.topic_name] = counts.get(publisher.topic_name, 0) + publisher.sent
    if counts:
        node.get_logger().info('published: ' + ' '.join(f'{t}={n}' for t, n in counts.items()))


class Diagnostics:
    """Publishes DiagnosticArray on /diagnostics and logs rejected input, throttled.

    A reliable publisher drops what it sends before discovery matched a subscriber, and
    nodes report their start-up state at once: until some subscriber (a monitor, the
    recorder) has matched, the latest ``UNSENT_LIMIT`` arrays wait and go out first."""

    UNSENT_LIMIT = 20

    LEVELS = {
        'ok': DiagnosticStatus.OK,
        'warn': DiagnosticStatus.WARN,
        'error': DiagnosticStatus.ERROR,
        'stale': DiagnosticStatus.STALE,
    }

    def __init__(self, node: Node, hardware_id: str = 'simulation') -> None:
        self._node = node
        self._hardware_id = hardware_id
        self._publisher = node.create_publisher(
            DiagnosticArray, DIAGNOSTICS_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self._last_log: dict[str, float] = {}  # what -> time.monotonic() of its last log
        self._unsent: deque[DiagnosticArray] = deque(maxlen=self.UNSENT_LIMIT)
        self._lock = threading.Lock()  # nodes publish from worker threads too
        self.rejected: dict[str, int] = {}  # reason key -> count

    def publish(
        self, name: str, level: str, message: str, values: Mapping[str, object] | None = None
    ) -> None:
        """Publish the status ``name`` (prefixed with the node's name) at ``level`` ('ok',
        'warn', 'error' or 'stale') with ``message`` and ``values`` (as strings). Until a
        subscriber has matched, the latest ``UNSENT_LIMIT`` arrays are held back."""
        status = DiagnosticStatus(
            level=self.LEVELS[level],
            name=f'{self._node.get_name()}: {name}',
            message=message,
            hardware_id=self._hardware_id,
            values=[KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()],
        )
        array = DiagnosticArray(status=[status])
        array.header.stamp = self._node.get_clock().now().to_msg()
        with self._lock:
            if self._publisher.get_subscription_count() == 0:
                self._unsent.append(array)
                return
            while self._unsent:
                self._publisher.publish(self._unsent.popleft())
            self._publisher.publish(array)

    def reject(self, what: str, error: Exception | str, throttle_s: float = 2.0) -> None:
        """Count and report bad input ``what`` (e.g. a topic); log at most every
        ``throttle_s`` [s] per kind of input."""
        self.rejected[what] = self.rejected.get(what, 0) + 1
        now = time.monotonic()
        if now - self._last_log.get(what, -math.inf) >= throttle_s:
            self._last_log[what] = now
            self._node.get_logger().warning(
                f'rejected {what}: {error} ({self.rejected[what]} so far)'
            )
        self.publish(f'rejected {what}', 'warn', str(error), {'count': self.rejected[what]})


_R = TypeVar('_R')


def guarded(what: str) -> Callable[[Callable[..., _R]], Callable[..., _R | None]]:
    """Decorate a node's timer, subscription or service callback so that no exception
    escapes it to the executor (that would end the process). An unexpected one goes to
    the node's ``on_internal_error(what, error)`` if it has one (pa10_ik_node stops the
    arm there), else it is reported as rejected ``what`` (one throttled log line and a
    diagnostic); a service callback ``(request, response)`` then answers success=false
    with the error. Expected bad input is rejected inside the callbacks with a better
    reason."""

    def decorate(callback: Callable[..., _R]) -> Callable[..., _R | None]:
        @functools.wraps(callback)
        def wrapper(self: Any, *args: Any) -> _R | None:  # self: the node, duck-typed
            try:
                return callback(self, *args)
            except Exception as error:  # noqa: BLE001 - the root rule: nothing escapes
                handler = getattr(self, 'on_internal_error', None)
                if handler is not None:
                    handler(what, error)
                else:
                    self.diagnostics.reject(what, f'{type(error).__name__}: {error}')
                if len(args) == 2 and hasattr(args[1], 'success'):  # a service response
                    response = args[1]
                    response.success, response.message = False, f'{what}: {error}'
                    return response
                return None

        return wrapper

    return decorate


class DeferredServiceExecutor(MultiThreadedExecutor):
    """A MultiThreadedExecutor that hands the requests of services whose callback has a
    ``deferred_request(request, header)`` attribute to it instead of calling the
    callback, so the service answers later with ``send_response`` and no executor thread
    waits (rclpy's coroutine callbacks would busy-spin the executor while they wait)."""

    def _take_service(self, srv: Service) -> Callable[[], Coroutine[None, None, None]] | None:
        deferred = getattr(srv.callback, 'deferred_request', None)
        if deferred is None:
            return super()._take_service(srv)
        try:
            with srv.handle:
                # rclpy annotates srv_type with an unbound TypeVar; it is a service type.
                request, header = srv.handle.service_take_request(srv.srv_type.Request)  # type: ignore[attr-defined]
        except InvalidHandle:
            return None

        async def _execute() -> None:
            if header is not None:
                deferred(request, header)

        return _execute


class DeferredCallback:
    """A service callback for ``DeferredServiceExecutor``: it hands each request to
    ``deferred_request(request, header)``; called as a plain callback (by another
    executor) it runs ``blocking(request, response)``, which waits on the calling thread."""

    def __init__(
        self, deferred_request: Callable[[Any, Any], None], blocking: Callable[[Any, Any], Any]
    ) -> None:  # ROS requests of any type
        self.deferred_request = deferred_request
        self._blocking = blocking

    def __call__(self, request: Any, response: Any) -> Any:
        """Called as a plain service callback: ``blocking(request, response)``, on the
        calling thread; returns its response."""
        return self._blocking(request, response)


def fastdds_profile() -> Path:
    """The graph's Fast DDS profile (config/fastdds.xml: a shared-memory segment large
    enough for image bursts, 50 ms heartbeats), installed or in the source tree."""
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory('vgm_common')) / 'config' / 'fastdds.xml'
    except (ImportError, LookupError):
        return Path(__file__).resolve().parent.parent / 'config' / 'fastdds.xml'


def use_fastdds_profile(environ: MutableMapping[str, str] = os.environ) -> None:
    """Point Fast DDS at fastdds_profile() unless the user chose a profile."""
    if not any(environ.get(k) for k in FASTDDS_PROFILE_VARIABLES):
        for variable in FASTDDS_PROFILE_VARIABLES:
            environ[variable] = str(fastdds_profile())


def init_rclpy(args: list[str] | None = None) -> None:
    """``rclpy.init`` as every node of the graph does it: with our Fast DDS profile
    (use_fastdds_profile) and without rclpy's signal handlers (the caller installs its
    own, so shutdown code still has a valid context)."""
    use_fastdds_profile()
    with _stderr_kept_on_success():
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)


@contextlib.contextmanager
def _stderr_kept_on_success() -> Iterator[None]:
    """Hold back what this process writes to stderr (file descriptor 2, so rcl's own C
    logging too) in the block: written out if the block succeeds, dropped if it raises.
    rcl logs 'Failed to parse global arguments' before raising the error that says what
    failed; the caller reports that one in a single line."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        held.seek(0)
        os.write(2, held.read())  # reached only on success


# Fast DDS 2.x reads the first, 3.x the second.
FASTDDS_PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


POLL_PERIOD = 0.1  # [s] how often spinning checks a node's exit request

# What signal.signal takes and returns: a function, SIG_DFL / SIG_IGN, or None.
_SignalHandler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None


def run_node(
    node_class: Callable[[], Node],
    args: list[str] | None = None,
    executor_class: Callable[[], Executor] = SingleThreadedExecutor,
) -> int:
    """Construct and spin ``node_class`` until Ctrl-C, SIGTERM, external shutdown or the
    node's own exit request; returns the process exit status.

    Ctrl-C and SIGTERM end construction by KeyboardInterrupt and spinning within
    ``POLL_PERIOD`` (rclpy's own signal handler would invalidate the context first), so
    the node can still log and publish while it stops; further signals are ignored until
    it has stopped. A VgmError during construction (bad parameter, bad scenario) is
    logged in one line with exit status 2, never as a traceback. The node may define,
    all optional:

    - ``exit_requested``: a ``threading.Event``; setting it, from any thread, ends spinning
      (within ``POLL_PERIOD``) as a signal does: playback done, the disk full.
    - ``drain()``: called once spinning ended; returns how long [s] at most to go on
      spinning, so messages the middleware delivered before the signal are still taken
      (a recorder). An exit request, or ``drained()`` returning true, ends it early.
    - ``close()``: called once the executor stopped, before ``wait_for_delivery`` and
      ``destroy_node``, so its last log lines and diagnostics still go out.
    - ``exit_status``: read after ``close()``; e.g. 1 when the node failed while running.
    - ``node_name``: a class attribute, names the error line when construction fails.
    - ``diagnostics``: a ``Diagnostics``; a clash of node names is reported there too.

    A ``--params-file`` that is missing or not YAML is one error line and exit status 2.
    """
    name = getattr(node_class, 'node_name', node_class.__name__)
    try:
        check_params_files(sys.argv[1:] if args is None else args)
        init_rclpy(args)
    except (VgmError, RCLError) as error:
        # Before rclpy is up its logger may not print: one line on stderr, as it would.
        first_line = str(error).split(', at /')[0].splitlines()[0]
        print(f'[ERROR] [{name}]: start-up error: {first_line}', file=sys.stderr, flush=True)
        return 2
    previous_handlers = _set_stop_signal_handler(_raise_keyboard_interrupt)
    node: Node | None = None
    executor: Executor | None = None
    status = 0
    try:
        node = node_class()
        for path in _params_files(sys.argv[1:] if args is None else args):
            for warning in params_file_section_warnings(
                path, node.get_fully_qualified_name(), node.has_parameter
            ):
                node.get_logger().warning(warning)
        node.create_timer(NAME_CHECK_PERIOD, _name_clash_check(node))
        executor = executor_class()
        executor.add_node(node)
        exit_requested = getattr(node, 'exit_requested', None) or threading.Event()
        # While spinning a signal only sets a flag: raised inside a callback it could fall
        # between a publish and its bookkeeping (the published counts).
        signalled = threading.Event()
        _set_stop_signal_handler(lambda signum, frame: signalled.set())
        _spin_until(executor, lambda: exit_requested.is_set() or signalled.is_set())
        _set_stop_signal_handler(signal.SIG_IGN)
        drain = getattr(node, 'drain', None)
        if drain is not None:
            drained = getattr(node, 'drained', lambda: False)
            _spin_until(executor, lambda: exit_requested.is_set() or drained(), timeout=drain())
    except VgmError as error:
        if node is None:
            rclpy.logging.get_logger(name).error(f'start-up error: {error}')
        else:
            node.get_logger().error(f'stopped on error: {error}')
        status = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        _set_stop_signal_handler(signal.SIG_IGN)  # a second Ctrl-C must not cut this short
        if executor is not None:
            _finish_callbacks(executor)
            executor.shutdown()
        if node is not None:
            close = getattr(node, 'close', None)
            if close:
                close()
            _log_published_counts(node)
            status = status or getattr(node, 'exit_status', 0)
            wait_for_delivery(node)
            node.destroy_node()
        rclpy.try_shutdown()
        for signum, handler in previous_handlers.items():
            signal.signal(signum, handler)
    return status


def _finish_callbacks(executor: Executor) -> None:
    """Let the callbacks a MultiThreadedExecutor handed to its threads run to their end
    before ``executor.shutdown()`` destroys its guard condition. rclpy 7.1's shutdown does
    not wait for them (it tests its shutdown flag after setting it); a callback ending
    after it triggers the destroyed guard, and its task's InvalidHandle was printed at
    exit as 'The following exception was never retrieved: cannot use Destroyable because
    destruction was requested'. None is cancelled: a cancelled one is a coroutine never
    awaited, which Python warns about at exit."""
    pool = getattr(executor, '_executor', None)
    if isinstance(pool, ThreadPoolExecutor):
        pool.shutdown(wait=True)


def check_params_files(argv: Sequence[str]) -> None:
    """Raise VgmError naming the file if a ``--params-file`` in ``argv`` is missing or is
    not a YAML mapping (rcl would fail with a traceback-length message)."""
    for path in _params_files(argv):
        try:
            content = yaml.safe_load(Path(path).read_text())
        except OSError as error:
            raise VgmError(f'cannot read params file {path}: {error.strerror}') from None
        except yaml.YAMLError as error:
            mark = getattr(error, 'problem_mark', None)
            where = f' (line {mark.line + 1})' if mark else ''
            raise VgmError(
                f'params file {path} is not valid YAML{where}: {getattr(error, "problem", error)}'
            ) from None
        if not isinstance(content, dict):
            raise VgmError(
                f'params file {path} must map node names to {{ros__parameters: {{...}}}}'
            )


NAME_CHECK_PERIOD = 2.0  # [s]


def _name_clash_check(node: Node) -> Callable[[], None]:
    """A timer callback that logs an error (once per clash) when another node with the
    same fully qualified name runs on the domain: ROS 2 allows it, but parameters and
    services of the two then answer for each other."""
    state = {'clashing': False}

    def check() -> None:
        me = (node.get_name(), node.get_namespace())
        count = sum(1 for entry in node.get_node_names_and_namespaces() if entry == me)
        clashing = count > 1
        if clashing and not state['clashing']:
            message = (
                f'{count} nodes named {node.get_fully_qualified_name()} run on this '
                'domain: their parameters and services are ambiguous; give one '
                'another name (--ros-args -r __node:=<name>)'
            )
            node.get_logger().error(message)
            diagnostics = getattr(node, 'diagnostics', None)
            if isinstance(diagnostics, Diagnostics):
                diagnostics.publish('node name', 'error', message, {'nodes': count})
        state['clashing'] = clashing

    return check


def _spin_until(
    executor: Executor, done: Callable[[], bool], timeout: float | None = None
) -> None:
    """Spin ``executor`` until ``done()`` is true, its context is shut down, or ``timeout``
    [s] passed (None: no limit)."""
    deadline = math.inf if timeout is None else time.monotonic() + timeout
    while not done() and executor.context.ok():
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return
        executor.spin_once(timeout_sec=min(remaining, POLL_PERIOD))


def _set_stop_signal_handler(handler: _SignalHandler) -> dict[signal.Signals, _SignalHandler]:
    """Handle SIGINT and SIGTERM with ``handler``; returns the previous handlers."""
    return {signum: signal.signal(signum, handler) for signum in (signal.SIGINT, signal.SIGTERM)}


def wait_for_delivery(node: Node, timeout: float = 2.0) -> bool:
    """Wait (at most ``timeout`` [s] in all) until every reliable subscriber has
    acknowledged what ``node`` published: destroying a publisher drops samples still in
    flight, and a recorder would miss the last few messages before shutdown."""
    deadline = time.monotonic() + timeout
    for publisher in node.publishers:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        if not publisher.wait_for_all_acked(Duration(nanoseconds=int(remaining * 1e9))):
            return False
    return True


def _raise_keyboard_interrupt(signum: int, frame: FrameType | None) -> NoReturn:
    raise KeyboardInterrupt
