"""Set keys of one table in a car's TOML text with tomlkit, in whichever style the person wrote
it (a `[pwm]` header with a comment, dotted `pwm.steer_left_us = ...` keys, an inline
`pwm = {...}`), keeping every comment, order and spacing tomlkit can keep. A line regex did this
before and turned the first two styles into a second `[pwm]` table that no TOML reader accepts.

Its own module so that only calibrating imports tomlkit: every carrt command imports
carrt/calibration_io.py (the CLI builds all parsers), and a car whose venv predates the
dependency must still drive; calibrating there says in one line what to install.
"""

from __future__ import annotations

from collections.abc import Mapping

import tomlkit
from tomlkit.container import OutOfOrderTableProxy
from tomlkit.exceptions import TOMLKitError
from tomlkit.items import InlineTable, Table


def update_section(text: str, section: str, values: Mapping[str, object]) -> str:
    """Set keys of the top-level table `section` in a TOML text, in whichever style it is
    written, keeping every other byte that tomlkit can keep. A missing table is added at the
    end; a `[car.pwm]` is some other table, not `pwm`. Raises ValueError when the text is not
    TOML, `section` is not a table, or tomlkit cannot make the edit."""
    try:
        return _update(text, section, values)
    except TOMLKitError as exc:  # a ParseError is a ValueError already; the others are not
        raise ValueError(str(exc) or type(exc).__name__) from exc


def _update(text: str, section: str, values: Mapping[str, object]) -> str:
    doc = tomlkit.parse(text)
    if section not in doc:
        table = tomlkit.table()
        table.update(values)
        doc.append(section, table)
        return _line_ends_as_in(text, tomlkit.dumps(doc))
    table = doc[section]
    if not isinstance(table, (Table, InlineTable, OutOfOrderTableProxy)):
        raise ValueError(f"{section} is not a table ({section} = {table.as_string().strip()})")
    added = {key: value for key, value in values.items() if key not in table}
    for key, value in values.items():
        if key in table:
            table[key] = value  # tomlkit keeps the key's comment and spacing
        elif isinstance(table, OutOfOrderTableProxy):  # dotted keys, maybe between others
            _append_key(_last_fragment(doc, section) or table, key, value)
        elif isinstance(table, Table):
            _append_key(table, key, value)
    if isinstance(table, InlineTable) and added:
        doc[section] = _extended_inline(table, added)
    return _line_ends_as_in(text, tomlkit.dumps(doc))


def _line_ends_as_in(original: str, edited: str) -> str:
    """tomlkit ends the lines it adds with LF: a file written on Windows keeps its CRLF."""
    if "\r\n" in original and "\n" not in original.replace("\r\n", ""):
        return edited.replace("\r\n", "\n").replace("\n", "\r\n")
    return edited


def _last_fragment(doc: tomlkit.TOMLDocument, section: str) -> Table | None:
    """The last part of a table spread over dotted keys: a new `pwm.x` goes after the last
    `pwm.` line, not between the first two."""
    parts = [item for key, item in doc.body if key is not None and key.key == section]
    return next((p for p in reversed(parts) if isinstance(p, Table)), None)


def _append_key(table: Table | OutOfOrderTableProxy, key: str, value: object) -> None:
    """A new key after the table's last key, not after the comment and blank line that tomlkit
    counts into the table's end but that a reader sees as the next table's introduction."""
    body = table.value.body if isinstance(table, Table) else []
    last = next((i for i in reversed(range(len(body))) if body[i][0] is not None), None)
    if last is None:
        table[key] = value
        return
    item = tomlkit.item(value)
    item.trivia.indent = body[last][1].trivia.indent  # an indented table stays indented
    if last == len(body) - 1:
        table[key] = item
    else:
        # tomlkit has no public insert: _insert_at is in every release from 0.12 to 0.15 (0.15
        # dropped the _insert_after this used, and a fresh install broke calibration)
        table.value._insert_at(last + 1, key, item)


def _extended_inline(table: InlineTable, added: Mapping[str, object]) -> InlineTable:
    """`pwm = { a = 1 }` with new keys, spaced as it is: `{ a = 1, b = 2 }` (tomlkit's own
    appends to an inline table lose the space before the brace in some tables, not others)."""
    text = table.as_string()
    pad = " " if text.startswith("{ ") else ""
    new = ", ".join(f"{k} = {tomlkit.item(v).as_string()}" for k, v in added.items())
    body = ", ".join(part for part in (text[1:-1].strip(), new) if part)
    return tomlkit.parse(f"v = {{{pad}{body}{pad}}}")["v"]
