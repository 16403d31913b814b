"""Declared stage parameters.

Each stage declares its parameters once, as a :class:`ParamSet` of :class:`Param` (name,
type, default, unit, one-line meaning, bounds). Defaults come from Table I of the paper
(see ``../shared/reference/algorithms.md`` section 2) wherever the paper gives one. The
declaration is validated when the stage starts, and the docs are generated from it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from gaitflow.errors import InputError, ParameterError


@dataclass(frozen=True)
class Param:
    """One declared parameter.

    ``choices`` restricts the value to a set; ``low``/``high`` bound a number (inclusive).
    """

    name: str
    type: type
    default: Any
    unit: str
    meaning: str
    low: float | None = None
    high: float | None = None
    choices: Sequence[Any] | None = None

    def validate(self, stage: str, value: Any) -> Any:
        """Return ``value`` coerced to the declared type, or raise ParameterError."""
        if self.type is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if self.type is bool and not isinstance(value, bool):
            raise ParameterError(stage, self.name, value, "must be true or false")
        if not isinstance(value, self.type):
            raise ParameterError(stage, self.name, value, f"must be {self.type.__name__}")
        if self.choices is not None and value not in self.choices:
            raise ParameterError(stage, self.name, value, f"must be one of {list(self.choices)}")
        if self.low is not None and value < self.low:
            raise ParameterError(stage, self.name, value, f"must be >= {self.low} {self.unit}")
        if self.high is not None and value > self.high:
            raise ParameterError(stage, self.name, value, f"must be <= {self.high} {self.unit}")
        return value


@dataclass(frozen=True)
class ParamSet:
    """The declared parameters of one stage."""

    stage: str
    params: tuple[Param, ...] = field(default_factory=tuple)

    def defaults(self) -> dict[str, Any]:
        return {p.name: p.default for p in self.params}

    def resolve(self, overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Defaults updated by ``overrides``, every value validated.

        Unknown names are an error: a typo in a config file must not pass silently.
        """
        overrides = dict(overrides or {})
        known = {p.name: p for p in self.params}
        unknown = sorted(set(overrides) - set(known))
        if unknown:
            raise ParameterError(self.stage, unknown[0], overrides[unknown[0]], "is not declared")
        out = {}
        for p in self.params:
            out[p.name] = p.validate(self.stage, overrides.get(p.name, p.default))
        return out

    def table(self) -> str:
        """A Markdown table of the declaration, for the README and ``--help``."""
        rows = ["| name | type | default | unit | meaning |", "|---|---|---|---|---|"]
        for p in self.params:
            rows.append(
                f"| {p.name} | {p.type.__name__} | {p.default!r} | {p.unit} | {p.meaning} |"
            )
        return "\n".join(rows)


def parse_overrides(items: Sequence[str]) -> dict[str, dict[str, Any]]:
    """``--param STAGE.NAME=VALUE`` options as per-stage overrides.

    ``["detect.split_cores=true", ...]`` -> ``{"detect": {"split_cores": True}}``. Values are
    parsed as YAML scalars (true, 0.5, text); each stage's ParamSet checks them when it
    starts. Raises InputError naming ``--param`` and the item when one is not of that form.
    """
    import yaml

    out: dict[str, dict[str, Any]] = {}
    for item in items:
        key, sep, value = item.partition("=")
        stage, dot, name = key.partition(".")
        if not sep or not dot or not stage or not name:
            raise InputError("--param", f"{item!r} is not STAGE.NAME=VALUE")
        out.setdefault(stage, {})[name] = yaml.safe_load(value)
    return out
