"""Run the Khronos glTF validator (npm package ``gltf-validator``) on a file.

Shared by every test that writes a glTF. Without Node or the package the
tests skip, except in CI (``CI=true``) or with
``BONECAP_REQUIRE_GLTF_VALIDATOR=1``, where a missing validator fails them.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _required() -> bool:
    return (os.environ.get("BONECAP_REQUIRE_GLTF_VALIDATOR") == "1"
            or os.environ.get("CI", "").lower() in ("1", "true"))


def run_validator(path: Path) -> dict:
    """The Khronos validator's report for ``path``; skip (or fail) if unavailable."""
    node = shutil.which("node")
    package = REPO / "node_modules" / "gltf-validator" / "package.json"
    missing = ("Node.js ('node') is not on PATH" if node is None
               else f"{package.parent} is missing (run 'npm install' in {REPO})" if not package.is_file()
               else None)
    if missing:
        if _required():
            pytest.fail(f"Khronos glTF validator required but unavailable: {missing}")
        pytest.skip(f"Khronos glTF validator unavailable: {missing} "
                    "(set BONECAP_REQUIRE_GLTF_VALIDATOR=1 to make this a failure)")
    done = subprocess.run([node, str(REPO / "tests" / "gltf_validate.mjs"), str(path)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def assert_clean(report: dict) -> None:
    issues = report["issues"]
    listing = "\n".join(f"{m['severity']} {m['code']} {m.get('pointer', '')}: {m['message']}"
                        for m in issues["messages"])
    assert (issues["numErrors"], issues["numWarnings"], issues["numInfos"], issues["numHints"]) == (0, 0, 0, 0), listing


