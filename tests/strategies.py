"""Hypothesis strategies for protocol messages, shared by the codec and agreement tests."""

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
