"""Shared fixtures: where the real public data lives, and how to run the CLI."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"


def pytest_configure(config):
    """The built template is cached per test session, in a folder of its own (not the user's
    cache: a test run neither reads an entry left by another version nor leaves one); the CLI
    subprocesses inherit it, so the embedded skeleton is built once, not once per command."""
    if "BONECAP_CACHE_DIR" not in os.environ:
        config._bonecap_cache = tempfile.mkdtemp(prefix="bonecap-test-cache-")
        os.environ["BONECAP_CACHE_DIR"] = config._bonecap_cache


def pytest_unconfigure(config):
    folder = getattr(config, "_bonecap_cache", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop("BONECAP_CACHE_DIR", None)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the project root; tests that need it skip without it."""
    if not SHARED.is_dir():
        pytest.skip(f"shared data not found at {SHARED}")
    return SHARED


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run ``python -m bonecap ARGS`` in a subprocess, as a user would."""
    return subprocess.run([sys.executable, "-m", "bonecap", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=300)


@pytest.fixture
def cli():
    return run_cli
