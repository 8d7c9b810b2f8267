"""`--set field=value` for any settings dataclass: one parser for training, export and the study.

Values are read by the field's declared type: int, float, str, bool (true/false, yes/no, on/off,
1/0), an optional field's `none`, and tuples as comma-separated lists. An unknown field, or a
value that is not of the field's type (NaN and infinities are not floats here: no setting
means them), is a UserError that names it (one line, exit 2), with a
did-you-mean for a near miss. (The car's TOML config has its own typed keys: carrt/config.py.)
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from typing import Any

from carrt.errors import UserError

TRUE, FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def parse_value(kind: str, text: str) -> Any:
    """`text` as a value of the annotation `kind` (a string: annotations are not evaluated)."""
    text = text.strip()
    if "None" in kind and text.lower() in ("", "none"):
        return None
    if kind.startswith("tuple"):
        inner = kind[kind.index("[") + 1 :].split(",")[0].strip()
        return tuple(parse_value(inner, part) for part in text.split(",") if part.strip())
    if kind.startswith("bool"):
        if text.lower() not in TRUE + FALSE:
            raise ValueError(text)
        return text.lower() in TRUE
    if kind.startswith("int"):
        return int(text)
    if kind.startswith("float"):
        value = float(text)
        if not math.isfinite(value):
            raise ValueError(text)
        return value
    return text


def apply_sets(settings: Any, items: list[str], where: str, *, frozen: tuple[str, ...] = ()) -> Any:
    """A copy of the dataclass `settings` with each `field=value` of `items` applied.
    `where` says where the fields are documented; `frozen` fields cannot be set this way."""
    fields = {f.name: str(f.type) for f in dataclasses.fields(settings) if f.name not in frozen}
    for item in items:
        name, eq, text = item.partition("=")
        name = name.strip()
        if not eq or not name:
            raise UserError(f"--set {item!r}: expected field=value")
        if name not in fields:
            close = difflib.get_close_matches(name, list(fields), n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise UserError(f"--set {name}: unknown field{hint} (see {where})")
        try:
            value = parse_value(fields[name], text)
        except ValueError:
            raise UserError(f"--set {item}: not a valid {fields[name]}") from None
        settings = dataclasses.replace(settings, **{name: value})
    return settings
