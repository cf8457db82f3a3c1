"""Two simulated hosts: Linux network namespaces joined by a veth pair, each with its
loopback up, an address on the link, a multicast route (DDS discovery) and the kernel
settings the ROS 2 DDS tuning guide asks for. Needs root and iproute2 (installed with
apt-get if missing); without them ``TwoHosts`` raises HostsError saying why."""

import os
import shutil
import subprocess

# Per network namespace (the ROS 2 DDS tuning guide): reassemble fragmented datagrams
# with a large buffer and drop incomplete ones quickly.
NAMESPACE_SYSCTLS = {'net.ipv4.ipfrag_high_thresh': '134217728', 'net.ipv4.ipfrag_time': '3'}
# Global (not per namespace): the socket buffer cap, which must admit the 4 MiB buffers of
# vgm_common's Fast DDS profile.
SOCKET_BUFFER = 4194304
GLOBAL_SYSCTLS = ('net.core.rmem_max', 'net.core.wmem_max')


class HostsError(RuntimeError):
    """The machine cannot make the simulated hosts; the message says why."""


class TwoHosts:
    """``with TwoHosts(tag) as hosts``: namespaces ``hosts.names['a']`` / ``['b']`` on
    10.<x>.<y>.1 / .2; ``hosts.prefix('b')`` runs a command on host b; everything is
    removed on exit, whatever happened."""

    def __init__(self, tag):
        tag = int(tag) % 10000
        self.names = {host: f'vgm{tag}{host}' for host in 'ab'}
        self.links = {host: f'vgm{tag}{host}0' for host in 'ab'}
        self.addresses = {
            host: f'10.{100 + tag // 250 % 100}.{tag % 250}.{i}' for i, host in enumerate('ab', 1)
        }

    def prefix(self, host):
        return ['ip', 'netns', 'exec', self.names[host]]

    def __enter__(self):
        if os.geteuid() != 0:
            raise HostsError('the multi-host test needs root to create network namespaces')
        if shutil.which('ip') is None:
            _run(['apt-get', 'install', '-y', '-q', 'iproute2'])
        self.__exit__()  # what a killed earlier run with this tag left behind
        try:
            for name in self.names.values():
                _run(['ip', 'netns', 'add', name])
            _run(
                [
                    'ip',
                    'link',
                    'add',
                    self.links['a'],
                    'type',
                    'veth',
                    'peer',
                    'name',
                    self.links['b'],
                ]
            )
            for host, name in self.names.items():
                link = self.links[host]
                _run(['ip', 'link', 'set', link, 'netns', name])
                _run(['ip', '-n', name, 'addr', 'add', f'{self.addresses[host]}/24', 'dev', link])
                _run(['ip', '-n', name, 'link', 'set', 'lo', 'up'])
                _run(['ip', '-n', name, 'link', 'set', link, 'up'])
                _run(['ip', '-n', name, 'route', 'add', '224.0.0.0/4', 'dev', link])
                for key, value in NAMESPACE_SYSCTLS.items():
                    _run([*self.prefix(host), 'sysctl', '-q', '-w', f'{key}={value}'])
            for key in GLOBAL_SYSCTLS:
                if int(_run(['sysctl', '-n', key]).strip()) < SOCKET_BUFFER:
                    _run(['sysctl', '-q', '-w', f'{key}={SOCKET_BUFFER}'])
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc_info):
        for name in self.names.values():  # deleting a namespace deletes its veth end
            subprocess.run(['ip', 'netns', 'del', name], capture_output=True)
        return False

    def set_link(self, up):
        """The link up or down (both ends see it: a cable pulled)."""
        _run(['ip', '-n', self.names['a'], 'link', 'set', self.links['a'], 'up' if up else 'down'])

    def transmitted_bytes(self, host):
        """Bytes host sent over the link (the veth's counter)."""
        path = f'/sys/class/net/{self.links[host]}/statistics/tx_bytes'
        return int(_run([*self.prefix(host), 'cat', path]))


def _run(argv):
    try:
        result = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise HostsError(f'{" ".join(argv)}: {error}') from error
    if result.returncode != 0:
        raise HostsError(f'{" ".join(argv)} failed: {result.stderr.strip()}')
    return result.stdout
