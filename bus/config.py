"""Zenoh session configuration, loopback-only by default.

One :class:`BusConfig` builds every session: mode (peer, client or router), explicit
listen and connect endpoints, multicast scouting off unless a config turns it on, and
TLS settings passed through to Zenoh. Defaults: stages are clients of a router on
``tcp/127.0.0.1:7447``; nothing listens on or connects to any other address.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from gaitflow.errors import ConfigError

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
MODES = ("peer", "client", "router")


@dataclass(frozen=True)
class BusConfig:
    """Everything needed to open a Zenoh session.

    ``tls`` is passed through as Zenoh's ``transport/link/tls`` section (for example
    ``root_ca_certificate``, ``listen_private_key``, ``listen_certificate``,
    ``enable_mtls``, ``connect_private_key``, ``connect_certificate``). ``extra`` holds
    further raw Zenoh settings as (json5 path, value) pairs, e.g. an access-control section.
    """

    mode: str = "client"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = (DEFAULT_ROUTER,)
    multicast_scouting: bool = False
    site: str = "clinic"
    tls: Mapping[str, Any] = field(default_factory=dict)
    extra: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"bus mode {self.mode!r} is not one of {MODES}")

    def router(self, listen: tuple[str, ...] = (DEFAULT_ROUTER,)) -> BusConfig:
        """The config of a router listening on ``listen``."""
        return replace(self, mode="router", listen=tuple(listen), connect=())

    def to_zenoh(self) -> Any:
        """Build a ``zenoh.Config``."""
        import zenoh

        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(self.mode))
        c.insert_json5("scouting/multicast/enabled", json.dumps(bool(self.multicast_scouting)))
        # Gossip scouting would make peers dial addresses learnt from others: keep links to
        # the endpoints we name.
        c.insert_json5("scouting/gossip/enabled", "false")
        c.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        c.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.tls:
            c.insert_json5("transport/link/tls", json.dumps(dict(self.tls)))
        for path, value in self.extra:
            c.insert_json5(path, json.dumps(value))
        return c

    @classmethod
    def from_mapping(cls, doc: Mapping[str, Any], source: str = "bus config") -> BusConfig:
        known = {"mode", "listen", "connect", "multicast_scouting", "site", "tls", "extra"}
        unknown = set(doc) - known
        if unknown:
            raise ConfigError(f"{source}: unknown bus key(s) {sorted(unknown)}")
        kw: dict[str, Any] = {}
        for key in ("mode", "site"):
            if key in doc:
                kw[key] = str(doc[key])
        for key in ("listen", "connect"):
            if key in doc:
                v = doc[key]
                if not isinstance(v, list) or not all(isinstance(e, str) for e in v):
                    raise ConfigError(f"{source}: {key} must be a list of endpoints")
                kw[key] = tuple(v)
        if "multicast_scouting" in doc:
            kw["multicast_scouting"] = bool(doc["multicast_scouting"])
        if "tls" in doc:
            kw["tls"] = dict(doc["tls"] or {})
        if "extra" in doc:
            kw["extra"] = tuple((str(k), v) for k, v in dict(doc["extra"] or {}).items())
        return cls(**kw)

    @classmethod
    def load(cls, path: str | Path) -> BusConfig:
        """Read the ``bus:`` section of a YAML/JSON file (or the whole file)."""
        p = Path(path)
        try:
            doc = yaml.safe_load(p.read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"{p}: cannot read bus config: {exc}") from exc
        if not isinstance(doc, dict):
            raise ConfigError(f"{p}: not a mapping")
        return cls.from_mapping(doc.get("bus", doc), str(p))
