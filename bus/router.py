"""A Zenoh router as a Python process (``gaitflow router``), so nothing outside pip is needed.

A router is a Zenoh session opened in mode ``router`` that listens on its endpoints
(``tcp/127.0.0.1:7447`` by default); stage processes are clients that connect to it.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from dataclasses import replace
from types import FrameType

from gaitflow.bus.config import DEFAULT_ROUTER, BusConfig

from gaitflow.errors import BusError


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that was free a moment ago (bind to port 0)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def local_endpoint(port: int | None = None) -> str:
    """``tcp/127.0.0.1:<port>`` (a free port when ``port`` is None)."""
    return f"tcp/127.0.0.1:{free_port() if port is None else port}"


def client_config(endpoint: str, site: str = "clinic", base: BusConfig | None = None) -> BusConfig:
    """A client config connecting only to ``endpoint`` (multicast scouting stays off)."""
    return replace(base or BusConfig(site=site), mode="client", listen=(), connect=(endpoint,))


class Router:
    """A Zenoh router session.

    Parameters
    ----------
    cfg : base config (TLS, extra settings, site); mode and endpoints are replaced.
    listen : endpoints to listen on.
    """

    def __init__(
        self, cfg: BusConfig | None = None, listen: tuple[str, ...] = (DEFAULT_ROUTER,)
    ) -> None:
        self.cfg = (cfg or BusConfig()).router(tuple(listen))
        self.session = None

    def start(self) -> Router:
        import zenoh

        try:
            self.session = zenoh.open(self.cfg.to_zenoh())
        except zenoh.ZError as exc:
            where = list(self.cfg.listen)
            raise BusError(f"cannot start a Zenoh router on {where}: {exc}") from exc
        return self

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None

    def __enter__(self) -> Router:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_port(endpoint: str, timeout: float = 5.0) -> None:
    """Wait until something accepts TCP connections at ``tcp/host:port``."""
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host, int(port)), timeout=0.2):
                return
        except OSError as exc:
            if time.monotonic() > deadline:
                raise BusError(f"nothing listens on {endpoint} after {timeout} s") from exc
            time.sleep(0.05)


def serve(cfg: BusConfig, listen: tuple[str, ...], ready: threading.Event | None = None) -> int:
    """Run a router until SIGINT/SIGTERM; return the exit code (0)."""
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with Router(cfg, listen):
            print(f"gaitflow router: listening on {', '.join(listen)}", flush=True)
            if ready is not None:
                ready.set()
            # Started by a launcher: exit with it, even if it was SIGKILLed.
            parent = int(os.environ.get("GAITFLOW_PARENT_PID", "0") or 0)
            while not stop.wait(0.2):
                if parent and os.getppid() != parent:
                    break
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    return 0
