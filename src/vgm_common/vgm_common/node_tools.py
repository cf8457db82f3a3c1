"""What every node does at its edges: typed parameters with descriptors and validation,
diagnostics on /diagnostics, throttled rejection of bad input, and a clean ``main``."""
import math
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from vgm_common.errors import VgmError
from vgm_common.qos import DEFAULT_QOS


class ParameterError(VgmError):
    """A parameter has a value of the wrong kind or out of range."""


@dataclass
class Param:
    """One declared parameter: ``default`` fixes its kind (bool, int, float, str, list)."""

    name: str
    default: Any
    description: str
    range: Optional[tuple] = None  # (min, max) for numbers, inclusive
    choices: Optional[Sequence[str]] = None
    check: Optional[Callable[[Any], Optional[str]]] = None  # returns a reason if bad
    read_only: bool = False
    kind: type = field(init=False)

    def __post_init__(self):
        self.kind = type(self.default)

    def coerce(self, value):
        """The value in this parameter's kind, or ParameterError with a reason."""
        if self.kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)  # `rate:=100` for a float parameter is what users type
        if self.kind is list:
            ok = isinstance(value, (list, tuple))
            value = list(value) if ok else value
            if ok and self.default and isinstance(self.default[0], float):
                value = [float(v) if isinstance(v, int) else v for v in value]
        elif not isinstance(value, self.kind) or (self.kind is int and isinstance(value, bool)):
            raise ParameterError(f'parameter {self.name!r}: expected {self.kind.__name__}, '
                                 f'got {value!r}', key=self.name, value=value)
        if self.kind is float and not math.isfinite(value):
            raise ParameterError(f'parameter {self.name!r}: must be finite, got {value}',
                                 key=self.name, value=value)
        if self.range and not self.range[0] <= value <= self.range[1]:
            raise ParameterError(f'parameter {self.name!r}: {value} is outside '
                                 f'[{self.range[0]}, {self.range[1]}]', key=self.name,
                                 value=value)
        if self.choices and value not in self.choices:
            raise ParameterError(f'parameter {self.name!r}: {value!r} is not one of '
                                 f'{", ".join(self.choices)}', key=self.name, value=value)
        reason = self.check(value) if self.check else None
        if reason:
            raise ParameterError(f'parameter {self.name!r}: {reason}', key=self.name,
                                 value=value)
        return value

    def descriptor(self):
        text = self.description + (f' One of: {", ".join(self.choices)}.' if self.choices else '')
        # Dynamic typing lets coerce() give the one-line error (and accept an integer
        # for a float) instead of rclpy raising a traceback at declaration.
        descriptor = ParameterDescriptor(description=text, read_only=self.read_only,
                                         dynamic_typing=self.default != [])
        if self.range and self.kind is int:
            descriptor.integer_range = [IntegerRange(from_value=self.range[0],
                                                     to_value=self.range[1])]
        return descriptor


class NodeParameters:
    """Declares ``params`` on ``node``, validates start-up values (raising
    ParameterError naming the parameter) and later changes (refused with a reason).
    Current values are attributes: ``self.params.rate``."""

    def __init__(self, node, params):
        self._node = node
        self._params = {p.name: p for p in params}
        values = {}
        for p in params:
            # rclpy cannot infer an array type from an empty default.
            default = Parameter.Type.STRING_ARRAY if p.default == [] else p.default
            try:
                value = node.declare_parameter(p.name, default, p.descriptor()).value
            except InvalidParameterTypeException as error:
                raise ParameterError(f'parameter {p.name!r}: {error}', key=p.name) from None
            values[p.name] = p.coerce([] if value is None else value)
        self._values = values
        node.add_on_set_parameters_callback(self._on_set)

    def __getattr__(self, name):
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(name) from None

    def _on_set(self, parameters):
        updates = {}
        for parameter in parameters:
            spec = self._params.get(parameter.name)
            if spec is None:
                continue
            if spec.read_only:
                return SetParametersResult(successful=False,
                                           reason=f'{spec.name} is read-only')
            try:
                updates[spec.name] = spec.coerce(parameter.value)
            except ParameterError as error:
                return SetParametersResult(successful=False, reason=str(error))
        self._values.update(updates)
        return SetParametersResult(successful=True)


class Diagnostics:
    """Publishes DiagnosticArray on /diagnostics and logs rejected input, throttled."""

    LEVELS = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN,
              'error': DiagnosticStatus.ERROR, 'stale': DiagnosticStatus.STALE}

    def __init__(self, node, hardware_id='simulation'):
        self._node = node
        self._hardware_id = hardware_id
        self._publisher = node.create_publisher(DiagnosticArray, '/diagnostics', DEFAULT_QOS)
        self._last_log = {}
        self.rejected = {}  # reason key -> count

    def publish(self, name, level, message, values=None):
        status = DiagnosticStatus(level=self.LEVELS[level],
                                  name=f'{self._node.get_name()}: {name}', message=message,
                                  hardware_id=self._hardware_id,
                                  values=[KeyValue(key=str(k), value=str(v))
                                          for k, v in (values or {}).items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self._node.get_clock().now().to_msg()
        self._publisher.publish(array)

    def reject(self, what, error, throttle_s=2.0):
        """Count and report bad input ``what`` (e.g. a topic); log at most every
        ``throttle_s`` [s] per kind of input."""
        self.rejected[what] = self.rejected.get(what, 0) + 1
        now = time.monotonic()
        if now - self._last_log.get(what, -math.inf) >= throttle_s:
            self._last_log[what] = now
            self._node.get_logger().warning(f'rejected {what}: {error} '
                                            f'({self.rejected[what]} so far)')
        self.publish(f'rejected {what}', 'warn', str(error),
                     {'count': self.rejected[what]})


def init_rclpy(args=None):
    """``rclpy.init`` as every node of the graph does it: with our Fast DDS profile (a
    shared-memory segment large enough for image bursts; see config/fastdds.xml) unless
    the user set one, and without rclpy's signal handlers (the caller installs its own,
    so shutdown code still has a valid context)."""
    if not any(os.environ.get(k) for k in _FASTDDS_PROFILE_VARIABLES):
        profile = Path(__file__).resolve().parent.parent / 'config' / 'fastdds.xml'
        try:
            from ament_index_python.packages import get_package_share_directory
            profile = Path(get_package_share_directory('vgm_common')) / 'config' / 'fastdds.xml'
        except (ImportError, LookupError):
            pass  # running from the source tree
        if profile.exists():
            for variable in _FASTDDS_PROFILE_VARIABLES:
                os.environ[variable] = str(profile)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)


# Fast DDS 2.x reads the first, 3.x the second.
_FASTDDS_PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def run_node(node_class, args=None, executor_class=SingleThreadedExecutor):
    """Construct and spin ``node_class`` until Ctrl-C, SIGTERM or external shutdown.

    Ctrl-C and SIGTERM both raise KeyboardInterrupt in the spinning thread (rclpy's own
    signal handler would invalidate the context first), so the node's ``close()`` can
    still log and publish before it is destroyed. A VgmError during construction (bad
    parameter, bad scenario) is reported in one line with exit status 2, never as a
    traceback.
    """
    init_rclpy(args)
    signal.signal(signal.SIGINT, _raise_keyboard_interrupt)
    signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)
    node = executor = None
    status = 0
    try:
        node = node_class()
        executor = executor_class()
        executor.add_node(node)
        executor.spin()
    except VgmError as error:
        name = node_class.__name__ if node is None else node.get_name()
        print(f'[{name}] error: {error}', file=sys.stderr, flush=True)
        status = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not cut this short
        if executor is not None:
            executor.shutdown()
        if node is not None:
            close = getattr(node, 'close', None)
            if close:
                close()
            wait_for_delivery(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return status


def wait_for_delivery(node, timeout=2.0):
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


def _raise_keyboard_interrupt(signum, frame):
    raise KeyboardInterrupt
