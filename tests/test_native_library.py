"""The firmware core library comes with the package, and a stale one is refused in one line."""

from __future__ import annotations

import pytest

from carrt.cli import main
from carrt.demo import DEMO_POLICY
from firmware_bridge import native
from firmware_bridge.core_sources import source_digest


@pytest.fixture
def sources_edited(monkeypatch):
    """As if a C file changed after the library was built: its digest no longer matches."""
    monkeypatch.setattr(native, "source_digest", lambda: "0123456789abcdef")
    monkeypatch.setattr(native, "_libs", {})
    yield
    native._libs.clear()


def test_the_library_comes_with_the_package_and_matches_its_sources():
    path = native.release_library()
    assert path.name.startswith("_fw_core.") and path.suffix == ".so"
    assert native.load_library().fwh_source_digest().decode() == source_digest()


def test_a_library_built_from_other_sources_is_refused(sources_edited):
    with pytest.raises(native.FirmwareBuildError, match=r"built from other C sources.*make"):
        native.FirmwareCore()


def test_the_cli_says_so_in_one_line(sources_edited, tmp_path, capsys):
    model = str(DEMO_POLICY)
    code = main(["drive", "--sim", "--autopilot", "--model", model, "--duration", "1",
                 "--out", str(tmp_path)])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "built from other C sources" in err[0]
