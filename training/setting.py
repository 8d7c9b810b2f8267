"""A training setting as data: its default, a one-line doc and the values it allows, beside it.

`setting()` declares a dataclass field the way carrt/config.py's `opt()` declares the car's; the
checks (`problems`), `carrt-train --settings` and docs/training.md's table (training/
settings_doc.py) are all read from those declarations, so a new setting is documented and
checked by being declared. Bounds: `lo`/`hi` inclusive, `above`/`below` exclusive; `choices` a
tuple of the allowed values. A float setting is finite wherever it is declared (NaN passes every
comparison, so a range alone would let it through).
"""

from __future__ import annotations

import dataclasses
import math
from numbers import Integral, Real
from typing import Any


def setting(default: Any, doc: str, *, lo: float | None = None, hi: float | None = None,
            above: float | None = None, below: float | None = None,
            choices: tuple | None = None) -> Any:  # fmt: skip
    """A settings field: default, doc, and its allowed range or choices."""
    meta = {"doc": doc, "lo": lo, "hi": hi, "above": above, "below": below, "choices": choices}
    return dataclasses.field(default=default, metadata=meta)


def allowed(spec: dataclasses.Field) -> str:
    """The values `spec` allows, as the listing and the docs write them ("" when any of its
    type): "first | all", "≥ 0", "> 0", "[0, 1)", "1 … 15"."""
    meta = spec.metadata
    if meta.get("choices"):
        return " | ".join(map(str, meta["choices"]))
    low = ("[", meta["lo"]) if meta.get("lo") is not None else ("(", meta.get("above"))
    high = ("]", meta["hi"]) if meta.get("hi") is not None else (")", meta.get("below"))
    if low[1] is not None and high[1] is not None:
        return f"{low[0]}{low[1]:g}, {high[1]:g}{high[0]}"
    if low[1] is not None:
        return f"{'≥' if low[0] == '[' else '>'} {low[1]:g}"
    if high[1] is not None:
        return f"{'≤' if high[0] == ']' else '<'} {high[1]:g}"
    return ""


def kind(spec: dataclasses.Field) -> str:
    """The field's type as written in its annotation ("int", "str | None", "tuple[str, ...]")."""
    return spec.type if isinstance(spec.type, str) else getattr(spec.type, "__name__", "")


def problem(spec: dataclasses.Field, value: Any) -> str | None:
    """What is wrong with `value` for the setting `spec`, in one line that names it; None when
    nothing is."""
    name, type_ = spec.name, kind(spec)
    if value is None:
        return None if "None" in type_ else f"{name} must be of type {type_}, got None"
    if type_.startswith("bool"):
        ok = isinstance(value, bool)
    elif type_.startswith("int"):
        ok = isinstance(value, Integral) and not isinstance(value, bool)
    elif type_.startswith("float"):
        ok = isinstance(value, Real) and not isinstance(value, bool)
        if ok and not math.isfinite(value):
            return f"{name} must be a finite number, got {value}"
    elif type_.startswith("str"):
        ok = isinstance(value, str)
    elif type_.startswith("tuple"):
        ok = isinstance(value, (tuple, list))
    else:
        ok = True
    if not ok:
        return f"{name} must be of type {type_}, got {value!r}"
    meta = spec.metadata
    if meta.get("choices") and value not in meta["choices"]:
        return f"{name} must be one of {', '.join(map(str, meta['choices']))}, got {value!r}"
    bounds = (("lo", "must be >=", lambda v, b: v >= b),
              ("above", "must be >", lambda v, b: v > b),
              ("hi", "must be <=", lambda v, b: v <= b),
              ("below", "must be <", lambda v, b: v < b))  # fmt: skip
    failed = [(key, words) for key, words, holds in bounds
              if meta.get(key) is not None and not holds(value, meta[key])]  # fmt: skip
    if failed:
        if allowed(spec).startswith(("[", "(")):  # a range with two ends: name both
            return f"{name} must be in {allowed(spec)}, got {value}"
        key, words = failed[0]
        return f"{name} {words} {meta[key]}, got {value}"
    return None


def problems(settings: Any) -> list[str]:
    """Every setting of the dataclass instance `settings` that its declaration refuses, one line
    each, in declaration order."""
    found = (problem(spec, getattr(settings, spec.name)) for spec in dataclasses.fields(settings))
    return [line for line in found if line]


def groups(cls: type) -> list[tuple[str, list[dataclasses.Field]]]:
    """`cls`'s fields under their headings: `cls.GROUPS` names each heading's first field."""
    specs = dataclasses.fields(cls)
    starts = {first: title for title, first in cls.GROUPS}
    out: list[tuple[str, list[dataclasses.Field]]] = []
    for spec in specs:
        if spec.name in starts or not out:
            out.append((starts.get(spec.name, ""), []))
        out[-1][1].append(spec)
    return out
