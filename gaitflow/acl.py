"""Zenoh access-control sections for the server's router.

The server's router is the only place where machines meet, so that is where access is
enforced (Zenoh ``access_control``, default deny). Subjects are matched by how they
connect:

- ``local``: the server's own stage processes, which reach the router over plain TCP on
  the loopback interface (``link_protocols: [tcp]``, ``interfaces: [lo]``). They may
  publish, subscribe and use liveliness anywhere under ``gaitflow/<site>/``;
- ``server``: the same rights for the server's certificate over TLS (a server stage run on
  another host of the server side);
- one subject per edge machine, matched by its TLS certificate's common name
  (``cert_common_names``, see :mod:`gaitflow.certs`). An edge may publish only under its
  own camera, ``gaitflow/<site>/<camera>/**``, may declare liveliness tokens only under
  ``gaitflow/<site>/@alive/<edge stage>/<camera>``, and may watch the router's liveliness
  token (how its uplink learns that the link is up). Nothing under a camera key is ever
  sent to an edge: patient data flows edge -> server only.

Rules name Zenoh message kinds: ``put``, ``delete``, ``declare_subscriber``, ``query``,
``reply``, ``declare_queryable``, ``liveliness_token``, ``liveliness_query``,
``declare_liveliness_subscriber``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from gaitflow.bus.keys import PREFIX, check_segment

ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
)
BOTH = ("ingress", "egress")


def router_token_key(site: str, machine: str = "server") -> str:
    """The liveliness token the server's router holds while it runs."""
    site, machine = check_segment("site", site), check_segment("machine", machine)
    return f"{PREFIX}/{site}/@alive/router/{machine}"


def uplink_token_key(site: str, camera: str) -> str:
    """The liveliness token an edge's uplink holds while connected."""
    return f"{PREFIX}/{check_segment('site', site)}/@alive/uplink/{check_segment('camera', camera)}"


def _rule(rid: str, messages: Sequence[str], flows: Sequence[str], keys: Sequence[str]) -> dict:
    return {
        "id": rid,
        "permission": "allow",
        "flows": list(flows),
        "messages": list(messages),
        "key_exprs": list(keys),
    }


def server_acl(
    site: str,
    edges: Mapping[str, str],
    edge_stages: Sequence[str] = (),
    server_machine: str = "server",
    local_interfaces: Sequence[str] = ("lo",),
) -> dict[str, Any]:
    """The ``access_control`` section of the server's router.

    Parameters
    ----------
    site : key-space site segment.
    edges : edge machine name (its certificate CN) -> the camera id it serves.
    edge_stages : stage names that run on edges (their liveliness keys are allowed).
    server_machine : the server's certificate CN.
    local_interfaces : interfaces of the plain-TCP listener for the server's own stages.
    """
    check_segment("site", site)
    # ``@alive`` is a verbatim chunk: ``**`` does not reach into it, so it is named.
    everything = [f"{PREFIX}/{site}/**", f"{PREFIX}/{site}/@alive/**"]
    rules = [
        _rule("server-all", ALL_MESSAGES, BOTH, everything),
    ]
    subjects: list[dict[str, Any]] = [
        {"id": "local", "link_protocols": ["tcp"], "interfaces": list(local_interfaces)},
        {"id": "server", "link_protocols": ["tls"], "cert_common_names": [server_machine]},
    ]
    policies: list[dict[str, Any]] = [
        {"id": "server-side", "rules": ["server-all"], "subjects": ["local", "server"]},
    ]
    router_key = router_token_key(site, server_machine)
    for machine, camera in sorted(edges.items()):
        check_segment("machine", machine)
        check_segment("camera", camera)
        alive = [f"{PREFIX}/{site}/@alive/{s}/{camera}" for s in (*edge_stages, "uplink")]
        alive += [f"{PREFIX}/{site}/@alive/{s}/{camera}/**" for s in (*edge_stages, "uplink")]
        rules += [
            # What the edge sends: its own camera's streams and its own liveliness tokens.
            _rule(f"{machine}-publish", ("put",), ("ingress",), [f"{PREFIX}/{site}/{camera}/**"]),
            _rule(f"{machine}-alive", ("liveliness_token",), ("ingress",), alive),
            # How the edge learns that the server is there: the router's token.
            _rule(
                f"{machine}-watch-in",
                ("declare_liveliness_subscriber", "liveliness_query"),
                ("ingress",),
                [router_key],
            ),
            _rule(f"{machine}-watch-out", ("liveliness_token", "reply"), ("egress",), [router_key]),
            # Subscriber declarations (not data) go to the edge so its publishers know the
            # server listens; a subscription to another camera's key never matches there.
            _rule(
                f"{machine}-interest",
                ("declare_subscriber",),
                ("egress",),
                [f"{PREFIX}/{site}/**"],
            ),
        ]
        subjects.append({"id": machine, "link_protocols": ["tls"], "cert_common_names": [machine]})
        policies.append(
            {
                "id": f"{machine}-policy",
                "rules": [
                    f"{machine}-publish",
                    f"{machine}-alive",
                    f"{machine}-watch-in",
                    f"{machine}-watch-out",
                    f"{machine}-interest",
                ],
                "subjects": [machine],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
