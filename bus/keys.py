"""Key expressions: ``gaitflow/<site>/<camera>/<stream>``, lowercase and hierarchical.

Liveliness tokens live under ``gaitflow/<site>/@alive/<stage>/<worker>``.
"""

from __future__ import annotations

import re

from gaitflow.errors import ConfigError

PREFIX = "gaitflow"
_SEGMENT = re.compile(r"^[a-z0-9][a-z0-9_\-]*$")


def check_segment(kind: str, value: str) -> str:
    """A key segment must be lowercase letters, digits, '_' or '-'."""
    if not isinstance(value, str) or not _SEGMENT.match(value):
        raise ConfigError(f"{kind} {value!r} is not a valid key segment (lowercase a-z0-9_-)")
    return value


def stream_key(site: str, camera: str, stream: str) -> str:
    """The key of one camera's stream."""
    return "/".join((PREFIX, check_segment("site", site), check_segment("camera", camera), stream))


def stream_selector(site: str, stream: str, camera: str = "*") -> str:
    """A key expression for a stream of one camera, or of every camera with ``*``."""
    cam = camera if camera == "*" else check_segment("camera", camera)
    return "/".join((PREFIX, check_segment("site", site), cam, stream))


def parse_key(key: str) -> tuple[str, str, str]:
    """``gaitflow/<site>/<camera>/<stream>`` -> (site, camera, stream)."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != PREFIX:
        raise ConfigError(f"key {key!r} is not gaitflow/<site>/<camera>/<stream>")
    return parts[1], parts[2], parts[3]


def liveliness_key(site: str, stage: str, worker: int | str = 0) -> str:
    return f"{PREFIX}/{check_segment('site', site)}/@alive/{stage}/{worker}"
