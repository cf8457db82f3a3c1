"""vgm_launch: start a set of nodes as separate processes from one params file.

The params file is an ordinary ROS 2 params file; each top-level key names a node, and
node names equal executable names, so ``sensor_sim: {ros__parameters: {...}}`` starts
``sensor_sim`` with ``--ros-args --params-file <file>``. The executable is looked up in
the install prefixes of AMENT_PREFIX_PATH (``<prefix>/lib/<package>/<node>``), the same
file ``ros2 run`` resolves. Every line a node prints is prefixed with its name. Ctrl-C
(or SIGTERM) stops all nodes, in reverse start order; so does the failure of one. The
exit status is non-zero if any node failed.

    vgm_launch graph.yaml [--nodes sensor_sim recorder] [--duration 30]
               [--set sensor_sim:scenario:=S1.yaml]
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any, TextIO

import yaml

from vgm_common.errors import VgmError

# Exit statuses that mean "stopped because we asked it to".
_CLEAN_STOP = {0, -signal.SIGINT, -signal.SIGTERM, 128 + signal.SIGINT, 128 + signal.SIGTERM}


class LaunchError(VgmError):
    """The launch cannot go on: a bad params file or ``--set``, or a node's executable not
    found; the message says which."""


def find_executable(name: str, prefixes: Iterable[str] | None = None) -> Path:
    """``<prefix>/lib/<package>/<name>`` from AMENT_PREFIX_PATH (first match)."""
    if prefixes is None:
        prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for prefix in prefixes:
        for candidate in sorted(Path(prefix, 'lib').glob(f'*/{name}')):
            if candidate.is_file() and os.access(candidate, os.X_OK):
                return candidate
    raise LaunchError(
        f'no executable {name!r} under lib/<package>/ in AMENT_PREFIX_PATH '
        '(did you source ros2_ws/install/setup.bash?)'
    )


def node_names(params_file: str | Path) -> list[str]:
    """The node names of a params file: its top-level keys without a leading ``/``, less
    the ``/**`` section. Raises LaunchError unless the file is a mapping."""
    data = yaml.safe_load(Path(params_file).read_text()) or {}
    if not isinstance(data, dict):
        raise LaunchError(f'{params_file}: expected node names as top-level keys')
    return [name.lstrip('/') for name in data if name != '/**']


class Launch:
    """Runs nodes as process groups; ``run()`` returns 0 if none failed."""

    def __init__(
        self,
        params_file: str | Path,
        nodes: Iterable[str] | None = None,
        overrides: Iterable[str] = (),
        out: TextIO = sys.stdout,
        command_prefixes: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        """``command_prefixes``: {node: argv} run before a node's executable, e.g.
        ``['ip', 'netns', 'exec', 'host_b']`` to start it on a simulated second host."""
        self.params_file = Path(params_file).resolve()
        available = node_names(self.params_file)
        self.nodes = list(nodes) if nodes else available
        unknown = [n for n in self.nodes if n not in available]
        if unknown:
            raise LaunchError(f'{params_file} has no section for {", ".join(unknown)}')
        self.overrides: dict[str, list[str]] = {n: [] for n in self.nodes}
        for item in overrides:
            node, sep, assignment = item.partition(':')
            if not sep or ':=' not in assignment or node not in self.overrides:
                raise LaunchError(
                    f'--set {item!r}: expected NODE:PARAM:=VALUE for a launched node'
                )
            self.overrides[node] += ['-p', assignment]
        self.command_prefixes = dict(command_prefixes or {})
        self.out = out
        self.processes: dict[str, subprocess.Popen[str]] = {}
        # every line each node printed
        self.logs: dict[str, list[str]] = {name: [] for name in self.nodes}
        self._lock = threading.Lock()
        self._stopping = False
        self._pumps: list[threading.Thread] = []
        self._width = max(len(n) for n in self.nodes)

    def _print(self, name: str, line: str) -> None:
        with self._lock:
            self.out.write(f'[{name.ljust(self._width)}] {line}')
            self.out.flush()

    def _pump(self, name: str, stream: IO[str]) -> None:
        for line in iter(stream.readline, ''):
            self.logs[name].append(line)
            self._print(name, line)

    def start(self) -> None:
        """Start every node, in order, as its own process group with the params file and
        its overrides, and print its output prefixed with its name. Raises LaunchError if
        a node's executable is not found."""
        for name in self.nodes:
            argv = [
                *self.command_prefixes.get(name, []),
                str(find_executable(name)),
                '--ros-args',
                '-r',
                f'__node:={name}',
                '--params-file',
                str(self.params_file),
                *self.overrides[name],
            ]
            self.processes[name] = subprocess.Popen(
                argv,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                text=True,
                bufsize=1,
                preexec_fn=_own_group_die_with_parent,
                env=_node_environment(),
            )
        # Threads only after every fork: preexec_fn is unsafe while other threads run.
        for name, process in self.processes.items():
            pump = threading.Thread(target=self._pump, args=(name, process.stdout), daemon=True)
            pump.start()
            self._pumps.append(pump)

    def log_text(self, name: str) -> str:
        """Everything node ``name`` printed so far, as one string."""
        return ''.join(self.logs[name])

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the nodes in reverse start order, so a recorder started first records
        everything the others published: SIGINT to each process group, SIGKILL after
        ``timeout`` [s]."""
        self._stopping = True
        for name, process in reversed(self.processes.items()):
            if stop_process_group(process, timeout=timeout):
                self._print('launch', f'{name} did not stop in {timeout:g} s: killed it\n')
        for thread in self._pumps:
            thread.join(timeout=1.0)  # the last lines a node printed are in self.logs

    def failed(self) -> list[str]:
        """Names of nodes that exited with an error (not because we stopped them)."""
        return [
            name
            for name, p in self.processes.items()
            if p.returncode is not None
            and p.returncode != 0
            and not (self._stopping and p.returncode in _CLEAN_STOP)
        ]

    def run(self, duration: float | None = None, until: Callable[[], bool] | None = None) -> int:
        """Start, wait until Ctrl-C, ``duration`` [s], ``until()`` is true, a node
        failing, or all nodes exiting; then stop everything."""
        self.start()
        started = time.monotonic()
        try:
            while True:
                codes = [p.poll() for p in self.processes.values()]
                if self.failed() or all(c is not None for c in codes):
                    break
                if duration is not None and time.monotonic() - started >= duration:
                    break
                if until is not None and until():
                    break
                time.sleep(0.05)
        except KeyboardInterrupt:
            self._print('launch', 'Ctrl-C: stopping all nodes\n')
        finally:
            failed_before_stop = self.failed()
            self.stop()
        for name in failed_before_stop:
            self._print(
                'launch', f'{name} failed with exit status {self.processes[name].returncode}\n'
            )
        return 1 if failed_before_stop or self.failed() else 0


def _node_environment() -> dict[str, str]:
    """The nodes' environment: unbuffered output (log lines in order) and, unless the
    user chose otherwise, one BLAS/OpenMP thread per node: a graph of several processes
    on a few cores stalls when each numpy spins up a thread per core."""
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    for variable in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS'):
        env.setdefault(variable, '1')
    return env


def _own_group_die_with_parent() -> None:
    """In the child before exec: its own process group, so a terminal's Ctrl-C reaches
    only the launcher, which stops the nodes in order; and SIGTERM when the launcher dies,
    even by SIGKILL, so no node outlives it (Linux prctl PR_SET_PDEATHSIG)."""
    os.setpgid(0, 0)
    _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


_PR_SET_PDEATHSIG = 1
_LIBC = ctypes.CDLL(None, use_errno=True)


def stop_process_group(
    process: subprocess.Popen[Any], sig: signal.Signals = signal.SIGINT, timeout: float = 10.0
) -> bool:
    """Stop a process started as its own process group (``start_new_session`` or
    ``Launch``), children included: ``sig`` to the group, SIGKILL if it has not exited
    after ``timeout`` [s]. Returns whether it had to be killed. Every launcher of the
    project's processes (``Launch``, the tests' and benches' helpers) stops them so.
    The group is signalled even when its leader has exited: its children may not have."""
    _signal_group(process, sig)
    try:
        process.wait(timeout)
        return False
    except subprocess.TimeoutExpired:
        _signal_group(process, signal.SIGKILL)
        process.wait()
        return True


def _signal_group(process: subprocess.Popen[Any], sig: signal.Signals) -> None:
    try:
        os.killpg(process.pid, sig)
    except ProcessLookupError:
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """The ``vgm_launch`` command; returns the exit status: 0 = no node failed, 1 = one
    did, 2 = bad params file or arguments, or a node's executable not found."""
    parser = argparse.ArgumentParser(prog='vgm_launch', description=__doc__.split('\n\n')[0])
    parser.add_argument('params_file', help='ROS 2 params file; top-level keys = nodes')
    parser.add_argument('--nodes', nargs='+', help='start only these nodes')
    parser.add_argument('--duration', type=float, help='stop everything after this [s]')
    parser.add_argument(
        '--set',
        action='append',
        default=[],
        metavar='NODE:PARAM:=VALUE',
        help='override one parameter of one node',
    )
    args = parser.parse_args(argv)
    # SIGTERM stops the nodes as cleanly as Ctrl-C. SIGINT is set too: a shell starts a
    # background job (`vgm_launch ... &` in a script, nohup) with SIGINT ignored, Python
    # then installs no handler, and the launcher would ignore the signal it is stopped by.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    try:
        launch = Launch(args.params_file, args.nodes, args.set)
    except (LaunchError, OSError, yaml.YAMLError) as error:
        print(f'vgm_launch: {error}', file=sys.stderr)
        return 2
    try:
        return launch.run(duration=args.duration)
    except LaunchError as error:
        launch.stop()
        print(f'vgm_launch: {error}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
