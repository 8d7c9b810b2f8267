"""One `--set field=value` parser for every settings dataclass (training, the study)."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from carrt.errors import UserError
from carrt.settings import apply_sets


@dataclass(frozen=True)
class Demo:
    steps: int = 10
    lr: float = 1e-3
    name: str = "x"
    on: bool = False
    seeds: tuple[int, ...] = (0,)
    noise: tuple[float, ...] = (0.0,)
    init: str | None = "run"


def test_values_are_read_by_the_fields_type():
    got = apply_sets(Demo(), ["steps=3", "lr=0.5", "name=y", "on=yes", "seeds=1,2",
                              "noise=0.5, 1", "init=none"], "Demo")  # fmt: skip
    assert got == Demo(3, 0.5, "y", True, (1, 2), (0.5, 1.0), None)


@pytest.mark.parametrize(
    "item, message",
    [("stesp=3", "unknown field (did you mean steps?) (see Demo)"), ("steps=many", "not a valid"),
     ("on=maybe", "not a valid"), ("steps", "expected field=value"),
     ("lr=nan", "lr=nan: not a valid float"), ("lr=inf", "not a valid float"),
     ("noise=0.5,-inf", "not a valid tuple")],
)  # fmt: skip
def test_bad_settings_are_one_line_user_errors(item, message):
    with pytest.raises(UserError, match=None) as info:
        apply_sets(Demo(), [item], "Demo")
    assert message in str(info.value) and "\n" not in str(info.value)
