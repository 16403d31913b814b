"""``gaitflow certs``: a clinic CA and one TLS certificate per machine (see gaitflow.certs)."""

from __future__ import annotations

import argparse


def _run(args: argparse.Namespace) -> int:
    from gaitflow.certs import DEFAULT_SANS, make_bundle

    machines = [m.strip() for m in args.machines.split(",") if m.strip()]
    sans = [*DEFAULT_SANS, *(s.strip() for s in (args.san or "").split(",") if s.strip())]
    issued = make_bundle(args.out, machines, sans=sans, days=args.days)
    print(f"clinic CA: {args.out}/ca.pem (keep {args.out}/ca-key.pem offline)")
    for m, i in issued.items():
        print(f"{m}: {i.cert} {i.key} (CN={m}, SANs: {', '.join([m, *sans])})")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "certs",
        help="make a clinic CA and a TLS certificate per machine",
        description="Write OUT/ca.pem, OUT/ca-key.pem and OUT/<machine>/{cert,key,ca}.pem. "
        "An existing CA in OUT is reused, so machines can be added later. Each certificate's "
        "common name is the machine name (the access-control rules match it); every "
        "certificate also names localhost and 127.0.0.1, plus --san.",
        epilog="Example: gaitflow certs --out certs --machines edge-1,edge-2,server "
        "--san 10.0.0.5,server.clinic.lan",
    )
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--machines", required=True, help="comma-separated machine names")
    p.add_argument(
        "--san", help="extra subject alternative names (IPs or DNS names), comma-separated"
    )
    p.add_argument("--days", type=int, default=825, help="certificate validity (default 825)")
    p.set_defaults(func=_run)
