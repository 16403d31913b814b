"""``gaitflow deploy``: render role configs, and run the deploy-side processes of a role.

- ``gaitflow deploy render``: write ``deploy/roles/*.yaml`` and
  ``deploy/observability/prometheus.yml`` from ``deploy/pipeline.yaml``
  (``--check`` only compares);
- ``gaitflow deploy router ROLE.yaml``: the router of a role config (on the server: TLS
  listener for edges, loopback listener for local stages, access control, liveliness token);
- ``gaitflow deploy uplink ROLE.yaml``: an edge's uplink to the server with its MCAP ring;
- ``gaitflow deploy watch ROLE.yaml``: export ``gaitflow_stage_up`` from liveliness.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gaitflow.errors import ConfigError


def _edges(text: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        if "=" not in item:
            raise ConfigError(f"--edges: {item!r} is not MACHINE=CAMERA")
        m, c = item.split("=", 1)
        out[m.strip()] = c.strip()
    return out


def _render(args: argparse.Namespace) -> int:
    from gaitflow import deployment
    from gaitflow.stages.graph import load

    kw = {}
    if args.edges:
        kw["edges"] = _edges(args.edges)
    for name in ("site", "server_address", "locate_on", "metrics_host", "certs_dir", "state_dir"):
        v = getattr(args, name)
        if v is not None:
            kw[name] = v
    if args.server_tls_port is not None:
        kw["server_tls_port"] = args.server_tls_port
    topo = deployment.Topology(**kw)
    files = deployment.render(load(args.pipeline), topo)
    out = Path(args.out) if args.out else deployment.deploy_dir()
    if args.check:
        bad = deployment.stale(out, files)
        if bad:
            print(f"stale role configs in {out}: {', '.join(bad)} (run gaitflow deploy render)")
            return 1
        print(f"role configs in {out} are up to date ({len(files)} files)")
        return 0
    for p in deployment.write(out, files):
        print(p)
    return 0


def _router(args: argparse.Namespace) -> int:
    from gaitflow.edgebuffer import run_router

    return run_router(args.role)


def _uplink(args: argparse.Namespace) -> int:
    from gaitflow.edgebuffer import run_uplink

    return run_uplink(args.role)


def _watch(args: argparse.Namespace) -> int:
    from gaitflow.edgebuffer import run_watch

    return run_watch(args.role, port=args.port)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "deploy",
        help="role configs (edge, server, all-in-one) and their router/uplink/watch processes",
        description=__doc__,
        epilog="Examples:\n  gaitflow deploy render --check\n"
        "  gaitflow deploy router deploy/roles/server.yaml\n"
        "  gaitflow deploy uplink deploy/roles/edge-1.yaml\n"
        "  gaitflow deploy watch deploy/roles/edge-1.yaml",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    dsub = p.add_subparsers(dest="deploy", metavar="ACTION", required=True)
    r = dsub.add_parser(
        "render",
        help="write deploy/roles/*.yaml and deploy/observability/prometheus.yml",
        epilog="Example: gaitflow deploy render --out /etc/gaitflow --server-address 10.0.0.5 "
        "--edges edge-1=cam-1,edge-2=cam-2",
    )
    r.add_argument("--pipeline", help="pipeline description (default: the packaged one)")
    r.add_argument("--out", help="output directory (default: deploy/ of the source tree)")
    r.add_argument("--check", action="store_true", help="only compare; exit 1 when stale")
    r.add_argument("--edges", help="MACHINE=CAMERA,... (default edge-1=cam-1,edge-2=cam-2)")
    r.add_argument("--site")
    r.add_argument("--server-address", help="address edges dial (default 127.0.0.1)")
    r.add_argument("--server-tls-port", type=int)
    r.add_argument("--locate-on", choices=("edge", "server"))
    r.add_argument("--metrics-host", help="metrics bind address (default 127.0.0.1)")
    r.add_argument("--certs-dir")
    r.add_argument("--state-dir")
    r.set_defaults(func=_render)
    for name, fn, helptext in (
        ("router", _router, "run the router of a role config"),
        ("uplink", _uplink, "run an edge's uplink (forwarding + MCAP ring)"),
        ("watch", _watch, "export gaitflow_stage_up from liveliness on 127.0.0.1"),
    ):
        q = dsub.add_parser(
            name,
            help=helptext,
            description=helptext,
            epilog=f"Example: gaitflow deploy {name} deploy/roles/"
            + ("server.yaml" if name == "router" else "edge-1.yaml"),
        )
        q.add_argument("role", help="role config YAML (deploy/roles/*.yaml)")
        if name == "watch":
            q.add_argument("--port", type=int, help="metrics port (default: the role's)")
        q.set_defaults(func=fn)
