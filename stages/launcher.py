"""Start, supervise and stop the whole pipeline: a router plus one process per stage worker.

:class:`Launcher` reads the graph (``deploy/pipeline.yaml``), starts ``gaitflow router``
and then every stage of the chosen role (and each replica) as its own process
(``python -m gaitflow.cli stage <name> ...``), in topological order. A supervisor thread:

- restarts a stage worker that died (non-zero exit or a signal) after an exponential
  backoff (``backoff_s`` doubling up to ``max_backoff_s``; reset after ``stable_s`` of
  good running), and logs one line per restart;
- does not restart a worker that exited 0 (a source that reached its end) or 2 (a
  configuration error: restarting cannot fix it);
- counts restarts in ``gaitflow_launcher_restarts_total`` on the launcher's own metrics
  endpoint (127.0.0.1, ``metrics_port``; 0 = a free port).

``stop()`` terminates stages upstream first (SIGTERM, then wait, so each drains and
flushes what it received before its consumers stop), SIGKILLs stragglers after
``stop_timeout_s``, and stops the router last. Child output is forwarded line by line to
the launcher's stderr with a ``[stage/worker]`` prefix.

Used by ``gaitflow run`` and, as a library, by ``gaitflow analyze``::

    with Launcher(graph, endpoint="tcp/127.0.0.1:7447") as la:
        la.wait_sources()
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gaitflow.bus.config import DEFAULT_ROUTER
from gaitflow.bus.router import wait_port
from gaitflow.stages.graph import Graph, Node
from gaitflow.stages.runtime import MetricsServer, worker_id
from prometheus_client import CollectorRegistry, Counter, Gauge

from gaitflow.errors import ConfigError, StageError

log = logging.getLogger("gaitflow.launcher")

ROLES = ("all", "edge", "server")
EXIT_CONFIG = 2


@dataclass(frozen=True)
class WorkerPlan:
    """One stage worker process to run: its stage, camera(s), replica and metrics port.

    ``metrics_port`` None = the launcher's default (a free port with ``stage_metrics``,
    else none); ``metrics_host`` None = the stage config's.
    """

    stage: str
    camera: str = "*"
    replicas: int = 1
    worker: int = 0
    metrics_port: int | None = None
    metrics_host: str | None = None

    @property
    def worker_id(self) -> str:
        return worker_id(self.camera, self.replicas, self.worker)

    def stage_args(self) -> list[str]:
        """The ``gaitflow stage`` options that make a process this worker."""
        argv = []
        if self.camera != "*":
            argv += ["--camera", self.camera]
        if self.replicas > 1:
            argv += ["--replicas", str(self.replicas), "--worker", str(self.worker)]
        if self.metrics_port is not None:
            argv += ["--metrics-port", str(self.metrics_port)]
        if self.metrics_host is not None:
            argv += ["--metrics-host", self.metrics_host]
        return argv


def plan_workers(nodes: Sequence[Node], cameras: Sequence[str] = ()) -> list[WorkerPlan]:
    """The worker processes of ``nodes`` on a machine serving ``cameras``.

    A ``per_camera`` node gets one worker per camera (when cameras are given); any other
    node its ``replicas`` workers, each taking every camera.
    """
    plan = []
    for n in nodes:
        if n.per_camera and cameras:
            plan += [WorkerPlan(n.name, camera=c) for c in cameras]
        else:
            plan += [WorkerPlan(n.name, replicas=n.replicas, worker=w) for w in range(n.replicas)]
    return plan


@dataclass
class Child:
    """One supervised process: the router or a stage worker (``worker``: its worker id)."""

    name: str
    worker: str
    argv: list[str]
    is_router: bool = False
    proc: subprocess.Popen[bytes] | None = None
    restarts: int = 0
    failures: int = 0
    started_at: float = 0.0
    restart_at: float | None = None
    state: str = "new"
    exit_code: int | None = None
    metrics_url: str | None = None
    ready: threading.Event = field(default_factory=threading.Event)
    lines: list[str] = field(default_factory=list)

    @property
    def label(self) -> str:
        return self.name if self.is_router else f"{self.name}/{self.worker}"


class Launcher:
    """Runs a pipeline graph as processes on one machine.

    Parameters
    ----------
    graph : the pipeline description.
    role : ``all``, ``edge`` or ``server``: which nodes to run.
    stages : run only these node names (default: every node of the role).
    endpoint : the router endpoint; the router listens there and stages connect to it.
    router : start a router (False: connect to one already running at ``endpoint``).
    config : stage config file passed to every stage (``--config``).
    graph_path : the graph file passed to every stage (default: the packaged one).
    stage_args : extra arguments for every stage (e.g. ``["--rate", "max"]``).
    metrics_port : the launcher's own /metrics (None = off, 0 = a free port).
    stage_metrics : give every stage a metrics endpoint on a free port.
    cameras : the cameras this machine serves: ``per_camera`` nodes get a worker for each
        (see :func:`plan_workers`).
    plan : the worker processes to run, instead of those planned from the graph (a
        rendered role file's, with their metrics ports; see ``gaitflow run --role-file``).
    """

    def __init__(
        self,
        graph: Graph,
        role: str = "all",
        stages: Sequence[str] | None = None,
        endpoint: str = DEFAULT_ROUTER,
        router: bool = True,
        config: str | Path | None = None,
        graph_path: str | Path | None = None,
        stage_args: Sequence[str] = (),
        metrics_port: int | None = None,
        stage_metrics: bool = False,
        backoff_s: float = 0.5,
        max_backoff_s: float = 10.0,
        stable_s: float = 30.0,
        stop_timeout_s: float = 10.0,
        settle_s: float = 0.2,
        python: str = sys.executable,
        env: Mapping[str, str] | None = None,
        echo: bool = True,
        cameras: Sequence[str] = (),
        plan: Sequence[WorkerPlan] | None = None,
    ) -> None:
        if role not in ROLES:
            raise ConfigError(f"role {role!r} is not one of {ROLES}")
        self.graph, self.role, self.endpoint = graph, role, endpoint
        nodes = [n for n in graph.order() if role == "all" or n.role == role]
        if stages is not None:
            unknown = sorted(set(stages) - {n.name for n in graph.nodes})
            if unknown:
                raise ConfigError(f"{graph.source}: no stage named {unknown[0]!r}")
            nodes = [n for n in nodes if n.name in set(stages)]
        self.nodes: list[Node] = nodes
        self.backoff_s, self.max_backoff_s, self.stable_s = backoff_s, max_backoff_s, stable_s
        self.stop_timeout_s, self.settle_s = stop_timeout_s, settle_s
        self.echo = echo
        self.env = dict(os.environ if env is None else env)
        base = [python, "-m", "gaitflow.cli"]
        self.children: list[Child] = []
        if router:
            self.children.append(
                Child("router", "0", [*base, "router", "--listen", endpoint], is_router=True)
            )
        if plan is None:
            plan = plan_workers(nodes, cameras)
        known = {n.name for n in graph.nodes}
        for wp in plan:
            if wp.stage not in known:
                raise ConfigError(f"{graph.source}: no stage named {wp.stage!r}")
            argv = [*base, "stage", wp.stage, "--connect", endpoint]
            if graph_path is not None:
                argv += ["--graph", str(graph_path)]
            if config is not None:
                argv += ["--config", str(config)]
            if stage_metrics and wp.metrics_port is None:
                wp = dataclasses.replace(wp, metrics_port=0)
            argv += wp.stage_args() + list(stage_args)
            self.children.append(Child(wp.stage, wp.worker_id, argv))
        self.registry = CollectorRegistry()
        self._restarts = Counter(
            "gaitflow_launcher_restarts",
            "Stage worker restarts after a crash",
            ("stage", "worker"),
            registry=self.registry,
        )
        self._up = Gauge(
            "gaitflow_launcher_stage_up",
            "1 while the stage worker process runs",
            ("stage", "worker"),
            registry=self.registry,
        )
        for c in self.children:
            if not c.is_router:  # expose every worker's series from the start, at 0
                self._restarts.labels(c.name, str(c.worker))
                self._up.labels(c.name, str(c.worker)).set(0)
        self.metrics_port = metrics_port
        self.metrics: MetricsServer | None = None
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._supervisor: threading.Thread | None = None

    # -- processes -------------------------------------------------------------------

    def _spawn(self, c: Child) -> None:
        env = dict(self.env)
        env["GAITFLOW_STAGE_RESTARTS"] = str(c.restarts)
        env["GAITFLOW_PARENT_PID"] = str(os.getpid())
        env.setdefault("PYTHONUNBUFFERED", "1")
        c.ready.clear()
        c.proc = subprocess.Popen(
            c.argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            # Own process group: a terminal's Ctrl-C reaches only the launcher, which then
            # stops the stages in order. Stages watch GAITFLOW_PARENT_PID to exit if the
            # launcher itself dies.
            process_group=0,
        )
        c.started_at = time.monotonic()
        c.state, c.exit_code, c.restart_at = "running", None, None
        if not c.is_router:
            self._up.labels(c.name, str(c.worker)).set(1)
        threading.Thread(
            target=self._pump, args=(c, c.proc), name=f"out-{c.label}", daemon=True
        ).start()

    def _pump(self, c: Child, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdout is not None
        for raw in proc.stdout:
            line = raw.decode(errors="replace").rstrip()
            c.lines.append(line)
            del c.lines[:-200]
            if " ready" in line or "listening on" in line:
                if "metrics http://" in line:
                    c.metrics_url = line.rsplit("metrics ", 1)[1].strip()
                c.ready.set()
            if self.echo:
                print(f"[{c.label}] {line}", file=sys.stderr, flush=True)
        proc.stdout.close()

    def start(self, ready_timeout_s: float = 30.0) -> Launcher:
        """Start the router (wait for its port), every stage, the supervisor and metrics."""
        if self.metrics_port is not None:
            self.metrics = MetricsServer(self.registry, self.metrics_port)
        for c in self.children:
            self._spawn(c)
            if c.is_router:
                wait_port(self.endpoint, timeout=ready_timeout_s)
        self._supervisor = threading.Thread(target=self._supervise, name="supervisor", daemon=True)
        self._supervisor.start()
        return self

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        """Wait until every stage worker said it is ready (subscribed, token declared)."""
        deadline = time.monotonic() + timeout_s
        for c in self.children:
            left = deadline - time.monotonic()
            if not c.ready.wait(max(0.0, left)):
                tail = "; ".join(c.lines[-3:])
                raise StageError(c.name, f"worker {c.worker} not ready after {timeout_s} s {tail}")

    def _supervise(self) -> None:
        while not self._stopping.wait(0.05):
            now = time.monotonic()
            with self._lock:
                for c in self.children:
                    self._check(c, now)

    def _check(self, c: Child, now: float) -> None:
        if c.state == "running" and c.proc is not None and c.proc.poll() is not None:
            rc = c.proc.returncode
            c.exit_code = rc
            if not c.is_router:
                self._up.labels(c.name, str(c.worker)).set(0)
            if self._stopping.is_set():
                c.state = "stopped"
                return
            how = f"signal {signal.Signals(-rc).name}" if rc < 0 else f"exit code {rc}"
            if rc == 0:
                c.state = "done"
                log.info("gaitflow run: %s finished (%s)", c.label, how)
                return
            if rc == EXIT_CONFIG:
                c.state = "failed"
                log.error("gaitflow run: %s failed with a configuration error, not restarted: %s",
                          c.label, c.lines[-1] if c.lines else how)  # fmt: skip
                return
            if now - c.started_at >= self.stable_s:
                c.failures = 0
            delay = min(self.max_backoff_s, self.backoff_s * 2**c.failures)
            c.failures += 1
            c.restart_at = now + delay
            c.state = "backoff"
            log.warning(
                "gaitflow run: %s died (%s); restart #%d in %.1f s",
                c.label,
                how,
                c.restarts + 1,
                delay,
            )
        elif c.state == "backoff" and c.restart_at is not None and now >= c.restart_at:
            c.restarts += 1
            if not c.is_router:
                self._restarts.labels(c.name, str(c.worker)).inc()
            self._spawn(c)

    def status(self) -> list[dict[str, Any]]:
        """One row per process: name, worker, pid, state, restarts, exit code, metrics."""
        with self._lock:
            return [
                {
                    "name": c.name,
                    "worker": c.worker,
                    "pid": c.proc.pid if c.proc is not None else None,
                    "state": c.state,
                    "restarts": c.restarts,
                    "exit_code": c.exit_code,
                    "metrics": c.metrics_url,
                }
                for c in self.children
            ]

    def child(self, name: str, worker: int | str = 0) -> Child:
        for c in self.children:
            if c.name == name and c.worker == str(worker):
                return c
        raise ConfigError(f"no process {name}/{worker}")

    def wait_sources(self, timeout_s: float | None = None) -> bool:
        """Wait until every source stage (a node without inputs) has finished."""
        sources = [c for c in self.children if not c.is_router and not self._node(c).inputs]
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while any(c.state in ("running", "backoff", "new") for c in sources):
            if deadline is not None and time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True

    def _node(self, c: Child) -> Node:
        return next(n for n in self.nodes if n.name == c.name)

    def _terminate(self, group: list[Child]) -> None:
        for c in group:
            if c.proc is not None and c.proc.poll() is None:
                c.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.stop_timeout_s
        for c in group:
            if c.proc is None:
                continue
            try:
                c.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("gaitflow run: %s did not stop in %.0f s: SIGKILL", c.label,
                            self.stop_timeout_s)  # fmt: skip
                c.proc.kill()
                c.proc.wait()
            c.exit_code = c.proc.returncode
            c.state = "stopped"
            if not c.is_router:
                self._up.labels(c.name, str(c.worker)).set(0)

    def stop(self) -> None:
        """Stop every stage, upstream first, then the router. Idempotent."""
        self._stopping.set()
        if self._supervisor is not None:
            self._supervisor.join()
        with self._lock:
            for n in self.nodes:  # topological order: producers drain before consumers
                group = [c for c in self.children if c.name == n.name and not c.is_router]
                if any(c.proc is not None and c.proc.poll() is None for c in group):
                    self._terminate(group)
                    # Let the last outputs of this stage cross the router before its
                    # consumers stop taking input.
                    time.sleep(self.settle_s)
                else:
                    self._terminate(group)
            self._terminate([c for c in self.children if c.is_router])
        if self.metrics is not None:
            self.metrics.close()
            self.metrics = None

    def __enter__(self) -> Launcher:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
