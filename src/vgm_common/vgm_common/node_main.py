"""A node's ``main``: rclpy with the project's DDS profile, params-file checks, clean stop on
SIGINT/SIGTERM, an executor that lets running work finish, and the exit status."""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import (
    Callable,
    Coroutine,
    Iterator,
    MutableMapping,
)
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, NoReturn

import rclpy
from rclpy._rclpy_pybind11 import RCLError
from rclpy.duration import Duration
from rclpy.exceptions import (
    InvalidHandle,
)
from rclpy.executors import (
    Executor,
    ExternalShutdownException,
    MultiThreadedExecutor,
    SingleThreadedExecutor,
)
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from vgm_common.diagnostics import Diagnostics, log_published_counts
from vgm_common.errors import VgmError
from vgm_common.parameters import (
    check_params_files,
    params_file_section_warnings,
    params_files_in_args,
)

if TYPE_CHECKING:
    from rclpy.service import Service


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
        for path in params_files_in_args(sys.argv[1:] if args is None else args):
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
            log_published_counts(node)
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
