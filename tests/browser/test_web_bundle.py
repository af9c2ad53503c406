"""The committed bundle (``services/web/dist``) is what ``build.mjs`` makes of ``services/web/src``:
a change to the viewer or the ops page that was not rebuilt (``make web``) fails here.

Needs Node.js and ``npm ci`` in ``services/web`` (esbuild and MapLibre are dependencies there):
``make test`` and ``.ci/run`` install them; without them the test fails, naming what is missing.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.integration.conftest import REPO

pytestmark = pytest.mark.integration

WEB = REPO / "services" / "web"
#: esbuild's content hash in an asset name (``viewer-O5YU2RF5.js``). It also depends on where the
#: inputs lie relative to the build folder, so a build elsewhere names identical bytes differently.
HASHED = re.compile(r"-[A-Z0-9]{8}(?=\.(?:js|css)\b)")


def _unhashed(name: str) -> str:
    return HASHED.sub("-HASH", name)


def _files(dist: Path) -> dict[str, bytes]:
    """Every file of a ``dist`` folder by its name without hash; the pages with their asset names
    unhashed too (the assets' bytes are compared on their own)."""
    return {
        _unhashed(p.name): _unhashed(p.read_text()).encode() if p.suffix == ".html" else p.read_bytes()
        for p in sorted(dist.iterdir())
    }


def test_the_committed_bundle_is_the_build_of_the_sources(tmp_path: Path) -> None:
    assert shutil.which("node"), "node is missing"
    assert (WEB / "node_modules" / "esbuild").is_dir(), "esbuild is missing: (cd services/web && npm ci)"
    work = tmp_path / "web"
    shutil.copytree(WEB / "src", work / "src")
    for name in ("build.mjs", "package.json"):
        shutil.copy(WEB / name, work / name)
    (work / "node_modules").symlink_to(WEB / "node_modules", target_is_directory=True)
    done = subprocess.run(
        ["node", "build.mjs"], cwd=work, capture_output=True, text=True, timeout=300, check=False
    )
    assert done.returncode == 0, f"build.mjs failed:\n{done.stdout}\n{done.stderr}"
    built, committed = _files(work / "dist"), _files(WEB / "dist")
    assert sorted(built) == sorted(committed), "services/web/dist is stale: run `make web` and commit it"
    stale = [name for name in built if built[name] != committed[name]]
    assert not stale, f"services/web/dist is stale ({', '.join(stale)}): run `make web` and commit it"
