"""What the real-browser test needs around the Foxglove app, all on loopback:

- ``ensure_chromium`` / ``ensure_studio``: Debian's chromium (apt-get) and npm's
  ``@foxglove/studio-base@1.48.0`` (its prebuilt browser bundle) with react/react-dom
  17.0.2 (their UMD builds), installed once into a cache outside git; a clear error when
  they cannot be had (the test fails, never skips).
- ``HostServer``: HTTP for the host page, the bundle, the layout and files (bags) with
  Range requests, as the app's remote-file source reads an MCAP.
- ``Relay``: a loopback WebSocket relay for that app, which speaks only the older
  ``foxglove.websocket.v1`` subprotocol: it accepts that and connects to live_view with
  ``foxglove.sdk.v1`` (same wire format), frames passed through unchanged.
- ``Chromium``: headless chromium driven over the DevTools protocol (a websockets
  client): navigate, evaluate JavaScript, take screenshots.
"""

import asyncio
import base64
import json
import os
import re
import shutil
import subprocess
import tempfile
import threading
import time
import urllib.request
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import websockets
from websockets.asyncio.client import connect as ws_connect
from websockets.asyncio.server import serve as ws_serve
from websockets.sync.client import connect as ws_sync_connect

STUDIO_VERSION = '1.48.0'
REACT_VERSION = '17.0.2'
CACHE_DIR = (
    Path(os.environ.get('XDG_CACHE_HOME', Path.home() / '.cache'))
    / 'vgm'
    / f'foxglove-studio-{STUDIO_VERSION}'
)
HOST_DIR = Path(__file__).resolve().parent / 'host'
CHROMIUM = '/usr/bin/chromium'
# As known to work on this machine kind: no background connections out (the network is
# closed), a fresh profile; software WebGL for the 3D panel.
CHROMIUM_FLAGS = [
    '--headless',
    '--no-sandbox',
    '--disable-gpu',
    '--disable-quic',
    '--no-first-run',
    '--disable-background-networking',
    '--disable-component-update',
    '--disable-sync',
    '--use-angle=swiftshader',
    '--enable-unsafe-swiftshader',
    '--hide-scrollbars',
    '--mute-audio',
]
OLD_SUBPROTOCOL = 'foxglove.websocket.v1'
SDK_SUBPROTOCOL = 'foxglove.sdk.v1'


class BrowserSetupError(RuntimeError):
    """What the browser test needs could not be installed; the message says what to do."""


def _run(argv, what, timeout):
    try:
        result = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise BrowserSetupError(f'{what}: {error}') from None
    if result.returncode != 0:
        tail = (result.stderr or result.stdout).strip().splitlines()[-5:]
        raise BrowserSetupError(f'{what} failed (exit {result.returncode}): ' + ' | '.join(tail))
    return result


def ensure_chromium():
    """The path of Debian's chromium, installed with apt-get if absent."""
    if Path(CHROMIUM).exists():
        return CHROMIUM
    if shutil.which('apt-get') is None:
        raise BrowserSetupError(
            "chromium is not installed and there is no apt-get: install Debian's chromium package"
        )
    env_note = 'apt-get install -y chromium (as root)'
    try:
        _run(['apt-get', 'install', '-y', '--no-install-recommends', 'chromium'], env_note, 900)
    except BrowserSetupError:
        _run(['apt-get', 'update'], 'apt-get update', 600)
        _run(['apt-get', 'install', '-y', '--no-install-recommends', 'chromium'], env_note, 900)
    if not Path(CHROMIUM).exists():
        raise BrowserSetupError(f'apt-get installed chromium but {CHROMIUM} does not exist')
    return CHROMIUM


def ensure_studio(cache_dir=CACHE_DIR):
    """``node_modules`` holding the Foxglove app bundle and React's UMD builds, installed
    with npm into ``cache_dir`` once."""
    modules = cache_dir / 'node_modules'
    wanted = [
        modules / '@foxglove' / 'studio-base' / 'assets' / 'index.js',
        modules / 'react' / 'umd' / 'react.production.min.js',
        modules / 'react-dom' / 'umd' / 'react-dom.production.min.js',
    ]
    if all(path.exists() for path in wanted):
        return modules
    if shutil.which('npm') is None:
        raise BrowserSetupError(
            f'npm is not installed: it is needed to fetch @foxglove/studio-base@{STUDIO_VERSION}'
        )
    cache_dir.mkdir(parents=True, exist_ok=True)
    (cache_dir / 'package.json').write_text('{"private": true}\n')  # npm stays in here
    _run(
        [
            'npm',
            'install',
            '--prefix',
            str(cache_dir),
            '--no-audit',
            '--no-fund',
            '--loglevel=error',
            f'@foxglove/studio-base@{STUDIO_VERSION}',
            f'react@{REACT_VERSION}',
            f'react-dom@{REACT_VERSION}',
        ],
        f'npm install @foxglove/studio-base@{STUDIO_VERSION} into {cache_dir}',
        900,
    )
    missing = [str(path) for path in wanted if not path.exists()]
    if missing:
        raise BrowserSetupError(f'npm install left out {missing}')
    return modules


# -- HTTP ------------------------------------------------------------------------------

_TYPES = {
    '.html': 'text/html',
    '.js': 'text/javascript',
    '.json': 'application/json',
    '.wasm': 'application/wasm',
    '.png': 'image/png',
    '.svg': 'image/svg+xml',
    '.woff2': 'font/woff2',
    '.woff': 'font/woff',
    '.ttf': 'font/ttf',
    '.css': 'text/css',
    '.mcap': 'application/octet-stream',
}
_RANGE = re.compile(r'bytes=(\d*)-(\d*)$')


class HostServer:
    """Serves ``routes`` {url prefix: directory or file} on 127.0.0.1 (a free port) with
    Range support; ``requests`` records (path, range header) for the test to check."""

    def __init__(self, routes):
        self.routes = {prefix: Path(target) for prefix, target in routes.items()}
        self.requests = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):  # noqa: N802 -- http.server's name
                server._serve(self)

            def do_HEAD(self):  # noqa: N802
                server._serve(self, head=True)

        self._httpd = ThreadingHTTPServer(('127.0.0.1', 0), Handler)
        self.port = self._httpd.server_address[1]
        self.url = f'http://127.0.0.1:{self.port}'
        self._thread = threading.Thread(target=self._httpd.serve_forever, daemon=True)
        self._thread.start()

    def _resolve(self, path):
        path = path.split('?', 1)[0]
        for prefix in sorted(self.routes, key=len, reverse=True):
            if path == prefix or path.startswith(prefix.rstrip('/') + '/'):
                target = self.routes[prefix]
                rest = path[len(prefix) :].lstrip('/')
                candidate = (target / rest) if rest else target
                if target.is_dir() and not rest:
                    candidate = target / 'index.html'
                candidate = candidate.resolve()
                if candidate.is_file() and (
                    candidate == target.resolve() or target.resolve() in candidate.parents
                ):
                    return candidate
        return None

    def _serve(self, handler, head=False):
        range_header = handler.headers.get('Range')
        self.requests.append((handler.path, range_header))
        file = self._resolve(handler.path)
        if file is None:
            handler.send_error(HTTPStatus.NOT_FOUND)
            return
        size = file.stat().st_size
        start, end = 0, size - 1
        status = HTTPStatus.OK
        if range_header:
            match = _RANGE.match(range_header.strip())
            if not match or not (match.group(1) or match.group(2)):
                handler.send_error(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
                return
            if match.group(1):
                start = int(match.group(1))
                end = min(int(match.group(2)), size - 1) if match.group(2) else size - 1
            else:  # the last N bytes
                start = max(size - int(match.group(2)), 0)
            if start > end or start >= size:
                handler.send_response(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
                handler.send_header('Content-Range', f'bytes */{size}')
                handler.end_headers()
                return
            status = HTTPStatus.PARTIAL_CONTENT
        handler.send_response(status)
        handler.send_header('Content-Type', _TYPES.get(file.suffix, 'application/octet-stream'))
        handler.send_header('Content-Length', str(end - start + 1))
        handler.send_header('Accept-Ranges', 'bytes')
        handler.send_header('Cache-Control', 'no-store')
        if status == HTTPStatus.PARTIAL_CONTENT:
            handler.send_header('Content-Range', f'bytes {start}-{end}/{size}')
        handler.end_headers()
        if head:
            return
        with open(file, 'rb') as stream:
            stream.seek(start)
            remaining = end - start + 1
            try:
                while remaining > 0:
                    block = stream.read(min(remaining, 1 << 20))
                    if not block:
                        break
                    handler.wfile.write(block)
                    remaining -= len(block)
            except (BrokenPipeError, ConnectionResetError):
                pass  # the app cancels reads it no longer needs

    def close(self):
        self._httpd.shutdown()
        self._httpd.server_close()


# -- WebSocket relay ---------------------------------------------------------------------


class Relay:
    """ws://127.0.0.1:<port> accepting ``foxglove.websocket.v1``, each client relayed to
    ``upstream_url`` over ``foxglove.sdk.v1``. Runs its own event loop in a thread."""

    def __init__(self, upstream_url):
        self.upstream_url = upstream_url
        self.connections = 0
        self.frames_down = 0
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._stop = None
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        if not self._ready.wait(10):
            raise RuntimeError('the relay did not start')
        self.url = f'ws://127.0.0.1:{self.port}'

    def _run(self):
        asyncio.set_event_loop(self._loop)
        self._loop.run_until_complete(self._main())

    async def _main(self):
        self._stop = asyncio.Event()
        async with ws_serve(
            self._handle,
            '127.0.0.1',
            0,
            subprotocols=[OLD_SUBPROTOCOL],
            max_size=None,
            compression=None,
        ) as server:
            self.port = next(iter(server.sockets)).getsockname()[1]
            self._ready.set()
            await self._stop.wait()

    async def _handle(self, client):
        self.connections += 1
        async with ws_connect(
            self.upstream_url, subprotocols=[SDK_SUBPROTOCOL], max_size=None, compression=None
        ) as upstream:

            async def pipe(source, sink, count):
                try:
                    async for frame in source:
                        await sink.send(frame)
                        if count:
                            self.frames_down += 1
                except websockets.ConnectionClosed:
                    pass
                await sink.close()

            await asyncio.gather(pipe(upstream, client, True), pipe(client, upstream, False))

    def close(self):
        if self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)


# -- Chromium over the DevTools protocol -------------------------------------------------


class Chromium:
    """Headless chromium with one page, driven over the DevTools protocol."""

    def __init__(self, executable, width=1600, height=1000, log_path=None):
        self.profile = Path(tempfile.mkdtemp(prefix='vgm-chromium-'))
        self._log = open(log_path or self.profile / 'chromium.log', 'wb')
        self.log_path = Path(self._log.name)
        self.proc = subprocess.Popen(
            [
                executable,
                *CHROMIUM_FLAGS,
                f'--user-data-dir={self.profile}',
                '--remote-debugging-port=0',
                '--remote-allow-origins=*',
                f'--window-size={width},{height}',
                'about:blank',
            ],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        port_file = self.profile / 'DevToolsActivePort'
        deadline = time.monotonic() + 60
        while not (port_file.exists() and port_file.read_text().strip()):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise BrowserSetupError(f'chromium did not start: {self._tail()}')
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f'http://127.0.0.1:{port}/json/list', timeout=10) as answer:
            pages = [t for t in json.load(answer) if t['type'] == 'page']
        self._ws = ws_sync_connect(
            pages[0]['webSocketDebuggerUrl'], max_size=None, open_timeout=10
        ).__enter__()
        self._id = 0
        self.console = []  # console messages and exceptions of the page
        self.call('Runtime.enable')
        self.call('Page.enable')
        self.call(
            'Emulation.setDeviceMetricsOverride',
            width=width,
            height=height,
            deviceScaleFactor=1,
            mobile=False,
        )

    def _tail(self):
        self._log.flush()
        return ' | '.join(self.log_path.read_text(errors='replace').splitlines()[-5:])

    def call(self, method, timeout=60, **params):
        self._id += 1
        request_id = self._id
        self._ws.send(json.dumps({'id': request_id, 'method': method, 'params': params}))
        deadline = time.monotonic() + timeout
        while True:
            message = json.loads(self._ws.recv(timeout=max(deadline - time.monotonic(), 0.01)))
            if message.get('id') == request_id:
                if 'error' in message:
                    raise RuntimeError(f'{method}: {message["error"]}')
                return message.get('result', {})
            if message.get('method') == 'Runtime.consoleAPICalled':
                args = message['params'].get('args', [])
                self.console.append(
                    ' '.join(str(a.get('value', a.get('description', ''))) for a in args)
                )
            elif message.get('method') == 'Runtime.exceptionThrown':
                details = message['params']['exceptionDetails']
                self.console.append(
                    'exception: '
                    + str(details.get('exception', {}).get('description', details.get('text')))
                )

    def navigate(self, url):
        self.call('Page.navigate', url=url)

    def evaluate(self, expression):
        result = self.call(
            'Runtime.evaluate', expression=expression, returnByValue=True, awaitPromise=True
        )
        if 'exceptionDetails' in result:
            raise RuntimeError(f'{expression[:60]}...: {result["exceptionDetails"]}')
        return result['result'].get('value')

    def wait_for(self, expression, timeout, what):
        """Evaluate ``expression`` until it is truthy; returns its value."""
        deadline = time.monotonic() + timeout
        error = None
        while True:
            try:
                value = self.evaluate(expression)
            except RuntimeError as exception:  # e.g. no document.body while navigating
                value, error = None, exception
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f'timed out after {timeout:.0f} s waiting for {what}; '
                    f'last error: {error}; page console: {self.console[-8:]}'
                )
            time.sleep(0.25)

    def screenshot(self, path):
        data = self.call('Page.captureScreenshot', format='png')['data']
        Path(path).write_bytes(base64.b64decode(data))
        return Path(path)

    def close(self):
        try:
            if getattr(self, '_ws', None) is not None:
                self._ws.close()
        finally:
            if self.proc.poll() is None:
                self.proc.terminate()
                try:
                    self.proc.wait(10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
            self._log.close()
            shutil.rmtree(self.profile, ignore_errors=True)
