"""The node tools of the browser and glTF tests (tests/js: playwright-core, gltf-validator, three.js).

``make browser`` installs them with chromium; a test that finds node and npm but no ``node_modules``
(a fresh clone) runs ``npm ci`` itself, once, so a clean ``make test`` runs these tests too.
"""

from __future__ import annotations

import functools
import json
import shutil
import subprocess
from pathlib import Path

JS = Path(__file__).parent / "js"


@functools.cache
def node_modules() -> bool:
    """Whether tests/js/node_modules is there, installing it with ``npm ci`` when node and npm are."""
    if shutil.which("node") is None:
        return False
    if not (JS / "node_modules").is_dir() and shutil.which("npm") is not None:
        subprocess.run(["npm", "ci", "--no-audit", "--no-fund", "--silent"], cwd=JS, capture_output=True,
                       timeout=300, check=False)
    return (JS / "node_modules").is_dir()


def node_tool(package: str) -> bool:
    """Whether node and ``tests/js/node_modules/<package>`` are available."""
    return node_modules() and (JS / "node_modules" / package).is_dir()


def run_node(script: str, *args: str, timeout: float = 120) -> dict:
    """Run ``node tests/js/<script> args`` and parse the JSON object on its last stdout line."""
    out = subprocess.run(["node", str(JS / script), *args], capture_output=True, text=True, timeout=timeout,
                         check=False)
    assert out.stdout.strip(), out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])
