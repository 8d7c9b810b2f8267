"""Hypothesis strategies shared by tests: protocol messages (the codec and agreement tests) and
valid car.toml files written in every TOML style a person might use (the calibration edit)."""

from __future__ import annotations

from hypothesis import strategies as st

from firmware_bridge import messages as m


def _field_values(kind: str) -> st.SearchStrategy[int]:
    size, signed = m.KINDS[kind][1], m.KINDS[kind][2]
    bits = 8 * size
    if signed:
        return st.integers(-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
    return st.integers(0, (1 << bits) - 1)


def message_of(message_cls: type) -> st.SearchStrategy:
    """Any message of that type, every field anywhere in its wire range."""
    kwargs = {name: _field_values(kind) for name, kind, _ in m.fields_of(message_cls)}
    return st.builds(message_cls, **kwargs)


any_message = st.one_of([message_of(cls) for cls in m.MESSAGES])
sequence = st.integers(0, 0xFFFF)


# ------------------------------------------------------------------ car.toml files, any style
def _tenths(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.integers(round(lo * 100), round(hi * 100)).map(lambda n: n / 100)


_TRICKY = ["[pwm]", "[receiver]  # x", "pwm.steer_left_us = 1", "a = { b = 1 }", "µs", "'", '"']
_STRING = st.one_of(st.sampled_from(_TRICKY), st.text(st.characters(codec="utf-8"), max_size=12))
# Each key's values keep any mix of them valid (pwm: left < centre < right, the receiver's
# centres a deadzone from each end), so every generated file loads.
CAR_KEYS = {
    "serial": {
        "port": _STRING,
        "baud": st.integers(9600, 4_000_000),
        "handshake_timeout_s": _tenths(0.2, 30),
    },
    "pwm": {
        "steer_left_us": st.integers(800, 1400),
        "steer_center_us": st.integers(1400, 1600),
        "steer_right_us": st.integers(1600, 2200),
        "throttle_reverse_us": st.integers(800, 1400),
        "throttle_neutral_us": st.integers(1400, 1600),
        "throttle_forward_us": st.integers(1600, 2200),
        "max_forward": _tenths(0, 1),
    },
    "camera": {"source": _STRING, "fps": _tenths(1, 240), "loop_video": st.booleans()},
    "receiver": {
        "controls": st.sampled_from(["pad", "receiver", "both"]),
        "steer_left_us": st.integers(800, 1300),
        "steer_center_us": st.integers(1400, 1600),
        "steer_right_us": st.integers(1700, 2200),
        "throttle_reverse_us": st.integers(800, 1300),
        "throttle_neutral_us": st.integers(1400, 1600),
        "throttle_forward_us": st.integers(1700, 2200),
        "deadzone_us": st.integers(10, 90),
        "estop_us": st.integers(800, 2200),
    },
}
CALIBRATED = {  # what `carrt calibrate` and `--receiver` write
    "pwm": ("throttle_neutral_us", "steer_center_us", "steer_left_us", "steer_right_us"),
    "receiver": ("steer_left_us", "steer_center_us", "steer_right_us", "throttle_reverse_us",
                 "throttle_neutral_us", "throttle_forward_us", "estop_us"),
}  # fmt: skip


def toml_value(draw, value: object) -> str:
    """A value in one of the ways TOML allows writing it (1500, 1_500, 0x5DC, 'literal')."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return draw(st.sampled_from([str(value), f"{value:_d}", f"0x{value:X}"]))
    if isinstance(value, float):
        return repr(value)
    escaped = "".join(
        "\\" + c if c in '"\\' else f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else c
        for c in value
    )
    literal_ok = "'" not in value and all(0x20 <= ord(c) != 0x7F or c == "\t" for c in value)
    return draw(st.sampled_from([f"'{value}'", f'"{escaped}"'] if literal_ok else [f'"{escaped}"']))


@st.composite
def car_toml_files(draw) -> tuple[str, str, dict[str, int]]:
    """(a valid car.toml, the section calibrated, its new values): each section absent, a
    `[table]` (header comment, quoted or spaced name, comments, indentation, a trailing comment
    block), dotted keys (maybe interleaved with other sections') or an inline table."""
    notes = iter(range(1_000_000))

    def comment() -> str:
        return f"# note-{next(notes)} " + draw(st.sampled_from(["", *_TRICKY]))

    def key_values(section: str) -> list[tuple[str, str]]:
        keys = draw(
            st.permutations(sorted(draw(st.sets(st.sampled_from(list(CAR_KEYS[section]))))))
        )
        return [(k, toml_value(draw, draw(CAR_KEYS[section][k]))) for k in keys]

    def maybe(text: str) -> str:
        return text if draw(st.booleans()) else ""

    top: list[str] = []
    tables: list[list[str]] = []
    for section in CAR_KEYS:
        style = draw(st.sampled_from(["absent", "table", "dotted", "inline"]))
        pairs = key_values(section)
        eq = draw(st.sampled_from([" = ", "=", "  =  "]))
        if style == "table":
            name = draw(st.sampled_from([section, f'"{section}"', f" {section} "]))
            indent = draw(st.sampled_from(["", "  ", "\t"]))
            lines = [f"[{name}]" + maybe("  " + comment())]
            for key, value in pairs:
                lines += [indent + comment()] if draw(st.booleans()) else []
                lines.append(f"{indent}{key}{eq}{value}" + maybe("  " + comment()))
            lines += [""] * draw(st.integers(0, 2)) + ([comment()] if draw(st.booleans()) else [])
            tables.append(lines)
        elif style == "dotted":
            quoted = draw(st.booleans())
            for key, value in pairs:
                top.append(f"{section}.{chr(34) + key + chr(34) if quoted else key}{eq}{value}")
        elif style == "inline":
            pad = draw(st.sampled_from(["", " "]))
            body = ", ".join(f"{k}{eq}{v}" for k, v in pairs)
            top.append(f"{section} = {{{pad}{body}{pad}}}" + maybe("  " + comment()))
    top = [*draw(st.permutations(top)), *([comment()] if draw(st.booleans()) else [])]
    lines = [maybe(comment()), *top, ""]
    for table in draw(st.permutations(tables)):
        lines += table
    newline = draw(st.sampled_from(["\n", "\r\n"]))
    text = newline.join(lines) + newline
    section = draw(st.sampled_from(sorted(CALIBRATED)))
    values = {k: draw(CAR_KEYS[section][k]) for k in CALIBRATED[section]}
    return text, section, values
