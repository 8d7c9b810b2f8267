"""Reading a JSON file a user named on a bench command line: a missing or unreadable one is a
UserError (one line, exit 2), never a traceback. Shared by the tools that compare results."""

from __future__ import annotations

import json
from pathlib import Path

from carrt.errors import UserError


def read_json(path: str, what: str):
    """The parsed file; `what` names the kind in the message ("results file", "carrt eval file")."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UserError(f"no such {what}: {path}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not a {what} ({exc.__class__.__name__})") from None
