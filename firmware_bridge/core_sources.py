"""Which C files make the firmware core's host library, and the digest that names a build.

Kept free of imports beyond the standard library because setup.py loads this file on its own
(before the package is importable) to compile the library, and firmware_bridge.native uses the
same digest to refuse a library built from other sources than the ones beside it.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

FIRMWARE_DIR = Path(__file__).resolve().parent / "firmware"
CORE_SRC = FIRMWARE_DIR / "carrt_fw" / "src"
HOST_SRC = FIRMWARE_DIR / "host"
SOURCES = (CORE_SRC / "fw_frame.c", CORE_SRC / "fw_core.c", CORE_SRC / "fw_rc.c",
           HOST_SRC / "fw_host.c")  # fmt: skip
HEADERS = (
    CORE_SRC / "fw_hal.h",
    CORE_SRC / "fw_frame.h",
    CORE_SRC / "fw_core.h",
    CORE_SRC / "fw_rc.h",
    CORE_SRC / "protocol_generated.h",
)
# The strict warnings every host build must pass (the AVR build adds -Wconversion).
WARNING_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-Wshadow")
# The extension module setup.py builds; loaded with ctypes, never imported (it has no PyInit).
LIBRARY_MODULE = "firmware_bridge._fw_core"


def source_digest() -> str:
    """16 hex digits over the names and bytes of every source and header, in a fixed order."""
    digest = hashlib.sha256()
    for path in SOURCES + HEADERS:
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]
