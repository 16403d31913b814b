"""``gaitflow run``: start a router and every pipeline stage as processes, supervise them."""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

import yaml

from gaitflow.bus.config import DEFAULT_ROUTER
from gaitflow.bus.router import free_port
from gaitflow.commands._bus_args import stop_on_signals
from gaitflow.deployment import load_role, role_plan, stage_config
from gaitflow.stages import graph as graph_mod
from gaitflow.stages.launcher import ROLES, Launcher
from gaitflow.stages.runtime import StageConfig

EXAMPLE = """\
Examples:
  gaitflow run
  gaitflow run --role edge --config edge.yaml
  gaitflow run --role server --cameras cam-1,cam-2     # label and gait: a worker per camera
  gaitflow run --role-file deploy/roles/server.yaml --no-router
  gaitflow run --graph my-pipeline.yaml --metrics-port 9100 --stage-metrics
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run the whole pipeline (router + every stage) and supervise it",
        description="Start a Zenoh router and every stage of the pipeline graph (and its "
        "replicas) as its own process; restart a crashed stage with exponential backoff; "
        "on SIGINT/SIGTERM stop the stages upstream first, then the router.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--graph", metavar="FILE", help="pipeline graph (default deploy/pipeline.yaml)")
    p.add_argument("--role", choices=ROLES, default="all", help="which stages to run")
    p.add_argument("--config", metavar="FILE", help="stage config passed to every stage")
    p.add_argument("--stage", action="append", help="run only this stage (repeatable)")
    p.add_argument(
        "--cameras",
        default="",
        help="cameras this machine serves (comma-separated): per-camera stages (label, "
        "gait) run one worker each",
    )
    p.add_argument(
        "--role-file",
        metavar="FILE",
        help="a rendered role (deploy/roles/*.yaml): run exactly its stage workers, with "
        "their metrics ports; --config defaults to the role's stage config",
    )
    p.add_argument(
        "--endpoint",
        default=None,
        help=f"router endpoint (default: the config's first connect endpoint, or {DEFAULT_ROUTER})",
    )
    p.add_argument("--no-router", action="store_true", help="use a router already running")
    p.add_argument(
        "--metrics-port", type=int, default=None, help="launcher /metrics port (0 = free port)"
    )
    p.add_argument(
        "--stage-metrics", action="store_true", help="give every stage a /metrics on a free port"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
    graph = graph_mod.load(args.graph)
    plan = None
    config = args.config
    if args.role_file:
        role = load_role(args.role_file)
        plan = role_plan(role)
        if config is None:
            path = Path(tempfile.mkdtemp(prefix="gaitflow-run-")) / "stages.yaml"
            path.write_text(yaml.safe_dump(stage_config(role)))
            config = str(path)
    cfg = StageConfig.load(config)
    endpoint = args.endpoint or (cfg.bus.connect[0] if cfg.bus.connect else DEFAULT_ROUTER)
    if endpoint.endswith(":0"):
        endpoint = f"{endpoint[:-2]}:{free_port()}"
    la = Launcher(
        graph,
        role=args.role,
        stages=args.stage,
        endpoint=endpoint,
        router=not args.no_router,
        config=config,
        graph_path=args.graph,
        metrics_port=args.metrics_port,
        stage_metrics=args.stage_metrics,
        cameras=[c.strip() for c in args.cameras.split(",") if c.strip()],
        plan=plan,
    )
    with stop_on_signals() as stop:
        la.start()
        if la.metrics is not None:
            print(f"gaitflow run: launcher metrics {la.metrics.url}", flush=True)
        try:
            while not stop.wait(0.2):
                rows = [r for r in la.status() if r["name"] != "router"]
                if rows and all(r["state"] in ("done", "failed") for r in rows):
                    break
        finally:
            la.stop()
    failed = [r for r in la.status() if r["state"] == "failed"]
    return 2 if failed else 0
