"""Reading a JSON file a user named on a research command line: a missing or unreadable one is a
UserError (one line, exit 2), never a traceback. Shared by the tools that compare results.

A name ending in .gz is read through gzip: research/results/ keeps its larger results files
compacted that way (the same JSON, smaller in the tree)."""

from __future__ import annotations

import gzip
import json
import zlib
from pathlib import Path

from carrt.errors import UserError


def read_json(path: str, what: str):
    """The parsed file; `what` names the kind in the message ("results file", "carrt eval file")."""
    try:
        raw = Path(path).read_bytes()
        return json.loads(gzip.decompress(raw) if str(path).endswith(".gz") else raw)
    except FileNotFoundError:
        raise UserError(f"no such {what}: {path}") from None
    except IsADirectoryError:
        raise UserError(f"{path}: a directory, not a {what}") from None
    except (json.JSONDecodeError, UnicodeDecodeError, gzip.BadGzipFile, EOFError, zlib.error) as e:
        raise UserError(f"{path}: not a {what} ({e.__class__.__name__})") from None
