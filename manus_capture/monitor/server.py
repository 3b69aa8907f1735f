"""Serving the monitor: uvicorn in a daemon thread, bound before any camera opens.

`start_monitor` binds the socket itself, in the caller's thread, so a port in use is one
MonitorError (exit code 2) before a recording begins, and the socket it checked is the one
uvicorn serves (no window for another process to take it). The server then runs in its own
daemon thread with its own event loop: whatever happens to it (a crash, a stop) ends only that
thread, never the recording that called it.
"""

from __future__ import annotations

import errno
import ipaddress
import secrets
import socket
import threading
import time
from dataclasses import dataclass, field

import uvicorn

from manus_core.errors import MonitorError

from .app import Monitor, build_app
from .source import MonitorSource

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
START_TIMEOUT_S = 10.0


def parse_address(text: str, default_host: str = DEFAULT_HOST) -> tuple[str, int]:
    """`[HOST:]PORT` (an IPv6 host in brackets) as (host, port)."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else default_host
    if not port.isdigit() or not 0 <= int(port) <= 65535 or (sep and not host):
        raise MonitorError(f"monitor address {text!r}: expected [HOST:]PORT, a port from 0 to 65535")
    return host, int(port)


def is_loopback(host: str) -> bool:
    """Whether every address `host` names is on this machine only (127.0.0.0/8, ::1, localhost)."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except OSError:
        return False
    return all(ipaddress.ip_address(info[4][0]).is_loopback for info in infos)


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on host:port; MonitorError naming the address when it cannot be had."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except OSError as exc:
        raise MonitorError(f"monitor: cannot serve on {host}:{port}: unknown host ({exc.strerror or exc})") from None
    sock = socket.socket(family, kind, proto)
    try:
        # a monitor that just stopped leaves its port in TIME_WAIT: that may be reused, a listener may not
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(64)
    except OSError as exc:
        sock.close()
        why = "is in use" if exc.errno == errno.EADDRINUSE else f"cannot be used ({exc.strerror or exc})"
        raise MonitorError(f"monitor: port {port} on {host} {why}; pick another with --monitor [HOST:]PORT") from None
    return sock


@dataclass
class MonitorServer:
    """A running monitor: its address (`url` carries the token when there is one), and `stop()`."""

    host: str
    port: int
    token: str | None
    token_generated: bool
    monitor: Monitor
    server: uvicorn.Server
    thread: threading.Thread
    error: str | None = field(default=None)   # what ended the server, when something did

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/" + (f"?token={self.token}" if self.token else "")

    @property
    def running(self) -> bool:
        return self.thread.is_alive()

    def stop(self, timeout_s: float = 5.0) -> None:
        """End the server (its event streams first); waits up to `timeout_s` for its thread."""
        self.monitor.closing = True
        self.server.should_exit = True
        self.thread.join(timeout_s)


def start_monitor(source: MonitorSource, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                  token: str | None = None) -> MonitorServer:
    """Serve `source` on host:port (port 0: any free port) and return once it answers.

    A host other than loopback needs a token: without one, one is generated (`token_generated`;
    the caller prints `url`, which carries it). Raises MonitorError when the port is taken."""
    generated = token is None and not is_loopback(host)
    if generated:
        token = secrets.token_urlsafe(16)
    sock = bind(host, port)
    app, monitor = build_app(source, token)
    config = uvicorn.Config(app, log_config=None, log_level="warning", access_log=False, lifespan="on",
                            timeout_graceful_shutdown=2)
    server = uvicorn.Server(config)

    def serve() -> None:
        try:
            server.run(sockets=[sock])
        except BaseException as exc:   # noqa: BLE001 - a dying monitor must not take anything else with it
            running.error = f"{type(exc).__name__}: {exc}"
        finally:
            sock.close()

    running = MonitorServer(host, sock.getsockname()[1], token, generated, monitor, server,
                            threading.Thread(target=serve, name=f"monitor:{port}", daemon=True))
    running.thread.start()
    deadline = time.monotonic() + START_TIMEOUT_S
    while not server.started and running.thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    if not server.started:
        running.stop(1.0)
        raise MonitorError(f"monitor: the server on {host}:{running.port} did not start "
                           f"({running.error or 'no answer within ' + str(START_TIMEOUT_S) + ' s'})")
    return running
