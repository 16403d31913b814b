"""``--param STAGE.NAME=VALUE`` options, parsed once for analyze and the benchmarks."""

from __future__ import annotations

import pytest

from gaitflow.errors import InputError
from gaitflow.params import parse_overrides


def test_overrides_are_grouped_by_stage_with_yaml_scalars() -> None:
    got = parse_overrides(
        ["detect.step6_saturated_only=true", "gait.xi=0.03", "detect.n=14", "label.x=text"]
    )
    assert got == {
        "detect": {"step6_saturated_only": True, "n": 14},
        "gait": {"xi": 0.03},
        "label": {"x": "text"},
    }
    assert parse_overrides([]) == {}


@pytest.mark.parametrize("item", ["detect", "detect=1", "detect.n", ".n=1", "detect.=1"])
def test_an_item_not_of_the_form_names_the_option_and_the_item(item: str) -> None:
    with pytest.raises(InputError) as err:
        parse_overrides([item])
    assert "--param" in str(err.value)
    assert repr(item) in str(err.value)
