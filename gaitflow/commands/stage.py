"""``gaitflow stage <name>``: run one stage of the pipeline graph alone, on the bus."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys

from gaitflow.bus import Bus
from gaitflow.errors import BusError
from gaitflow.stages import graph as graph_mod
from gaitflow.stages.runtime import StageConfig, serve

EXAMPLE = """\
Examples:
  gaitflow stage detect
  gaitflow stage detect --config stage.yaml --camera cam0 --metrics-port 9101
  gaitflow stage clean --replicas 2 --worker 1 --connect tcp/127.0.0.1:7447

The config file (YAML) may hold
  bus:     {connect: [tcp/127.0.0.1:7447], site: clinic}
  params:  {name: value}            stage parameters (validated at start)
  metrics: {port: 0, host: 127.0.0.1}
  runtime: {queue_size: 32, queue_policy: block-then-drop-oldest, reorder_timeout_s: 0.25}
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stage",
        help="run one pipeline stage on the bus",
        description="Run one stage (a node of the pipeline graph) as a bus process: it "
        "subscribes to its inputs, runs its core and publishes its outputs until SIGINT or "
        "SIGTERM, then drains its queue and flushes.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("name", help="stage name in the graph (e.g. detect)")
    p.add_argument("--config", metavar="FILE", help="YAML with bus:, params:, metrics:, runtime:")
    p.add_argument("--graph", metavar="FILE", help="pipeline graph (default deploy/pipeline.yaml)")
    p.add_argument("--camera", default=None, help="take one camera only (default: all)")
    p.add_argument("--replicas", type=int, default=None, help="number of workers N")
    p.add_argument("--worker", type=int, default=None, help="this worker's index i (0..N-1)")
    p.add_argument(
        "--metrics-port", type=int, default=None, help="Prometheus port (0 = pick a free one)"
    )
    p.add_argument(
        "--metrics-host", default=None, help="address /metrics binds (default 127.0.0.1)"
    )
    p.add_argument("--rate", choices=("1", "max"), default=None, help="source pacing")
    p.add_argument(
        "--connect",
        metavar="ENDPOINT",
        action="append",
        help="router endpoint (repeatable; overrides the config)",
    )
    p.add_argument(
        "--shm",
        choices=("auto", "off", "on"),
        default=None,
        help="Zenoh shared memory: auto (Zenoh default), off, on (explicit buffers)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=logging.INFO,
        stream=sys.stderr,
        format=f"gaitflow stage {args.name}: %(message)s",
    )
    cfg = StageConfig.load(args.config)
    graph = graph_mod.load(args.graph)
    node = graph.node(args.name)
    replicas = args.replicas if args.replicas is not None else None
    if replicas is None and args.worker is not None:
        replicas = node.replicas
    opt = cfg.options(
        camera=args.camera,
        replicas=replicas,
        worker=args.worker,
        metrics_port=args.metrics_port,
        metrics_host=args.metrics_host,
        rate=args.rate,
        shm=args.shm,
    )
    bus_cfg = cfg.bus
    if args.connect:
        bus_cfg = dataclasses.replace(bus_cfg, connect=tuple(args.connect))
    if not cfg.site_set:
        bus_cfg = dataclasses.replace(bus_cfg, site=graph.site)
    restarts = int(os.environ.get("GAITFLOW_STAGE_RESTARTS", "0") or 0)

    def ready(msg: str) -> None:
        print(f"gaitflow stage {args.name}: {msg}", flush=True)

    try:
        return serve(
            node,
            lambda: Bus(bus_cfg, shm=opt.shm),
            cfg.params_for(args.name),
            opt,
            on_ready=ready,
            restarts=restarts,
        )
    except BusError as exc:
        # The bus may come back (a router restarting): exit 1 so a launcher retries,
        # unlike configuration errors (exit 2).
        print(f"gaitflow stage: error: {exc}", file=sys.stderr)
        return 1
