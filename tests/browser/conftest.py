"""Browser tests: pytest starts the service (the integration fixtures), seeds data, and runs
``driver.mjs`` (playwright-core driving Debian's headless Chromium) for each scenario; the
screenshots land in ``test-artifacts/browser/``.

Needs: ``/usr/bin/chromium`` (``apt-get install -y chromium``), Node.js, and
``npm ci`` in ``services/web`` (playwright-core is a dev dependency there): ``.ci/run`` and
``make test`` install them. A machine without them fails these tests, naming what is missing.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from tests.integration.conftest import ARTIFACTS, REPO, make_isolated, pg  # noqa: F401 (fixtures)

DRIVER = Path(__file__).with_name("driver.mjs")
CHROMIUM = os.environ.get("CSR_CHROMIUM", "/usr/bin/chromium")
OUT = ARTIFACTS / "browser"


def _missing() -> str | None:
    if not Path(CHROMIUM).exists():
        return f"{CHROMIUM} is missing: apt-get install -y chromium"
    if shutil.which("node") is None:
        return "node is missing"
    if not (REPO / "services/web/node_modules/playwright-core").is_dir():
        return "playwright-core is missing: (cd services/web && npm ci)"
    return None


@pytest.fixture(scope="session")
def browser_ready() -> None:
    problem = _missing()
    assert problem is None, f"browser tests: {problem}"


def run_driver(scenario: str, **config: Any) -> dict[str, Any]:
    """Run one scenario of driver.mjs; returns what it saw (``checks``, ``screenshots``, ``errors``)."""
    config = {"out": str(OUT), "chromium": CHROMIUM, **config}
    for old in OUT.glob(f"{config.get('out_prefix', '')}{scenario}-*"):  # no stale screenshots
        old.unlink()
    done = subprocess.run(
        ["node", str(DRIVER), scenario, json.dumps(config)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
        check=False,
    )
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    assert done.returncode == 0 and lines, f"driver.mjs {scenario} failed:\n{done.stdout}\n{done.stderr}"
    result = json.loads(lines[-1])
    (OUT / f"{config.get('out_prefix', '')}{scenario}-result.json").write_text(json.dumps(result, indent=1))
    return result
