"""`carrt ... --view` as a real subprocess for the view tests: waits for the URL it prints,
keeps reading its output (so a full pipe never stalls it), stops it with SIGINT at the end."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


@dataclass
class Carrt:
    process: subprocess.Popen
    url: str  # as printed: with ?token=... when bound beyond localhost
    lines: list[str] = field(default_factory=list)

    @property
    def base(self) -> str:
        """http://127.0.0.1:PORT, whatever host name the URL shows."""
        port = self.url.split("://", 1)[1].split("/", 1)[0].rsplit(":", 1)[1]
        return f"http://127.0.0.1:{port}"

    @property
    def token(self) -> str | None:
        return self.url.split("token=", 1)[1] if "token=" in self.url else None


@contextlib.contextmanager
def carrt_with_view(argv: list[str], cwd: Path, timeout_s: float = 60.0) -> Iterator[Carrt]:
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy", "PYTHONPATH": path}
    process = subprocess.Popen(
        [sys.executable, "-m", "carrt", *argv],
        cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    lines: list[str] = []
    found = threading.Event()

    def read() -> None:
        for line in process.stdout:
            lines.append(line.rstrip("\n"))
            if line.startswith("view: "):
                found.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        deadline = time.monotonic() + timeout_s
        while not found.wait(0.1):
            assert process.poll() is None, "carrt ended before serving:\n" + "\n".join(lines)
            assert time.monotonic() < deadline, "no view URL printed:\n" + "\n".join(lines)
        url = next(line for line in lines if line.startswith("view: "))[len("view: ") :]
        yield Carrt(process, url, lines)
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def request(url: str, *, method: str = "GET", headers: dict | None = None) -> tuple[int, bytes]:
    req = urllib.request.Request(url, method=method, headers=headers or {},
                                 data=b"" if method == "POST" else None)  # fmt: skip
    try:
        with urllib.request.urlopen(req, timeout=10) as answer:
            return answer.status, answer.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def state(base: str, token: str | None = None) -> dict:
    status, body = request(f"{base}/state.json" + (f"?token={token}" if token else ""))
    assert status == 200, (status, body)
    return json.loads(body)
