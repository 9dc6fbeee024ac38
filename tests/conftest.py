"""Fixtures shared by several test files."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pipeline import Pipeline

NODE_DIR = Path(__file__).resolve().parent / "node"  # Foxglove's decoders (tests/node/package-lock.json)


@pytest.fixture
def tmpfs(tmp_path: Path) -> Iterator[Any]:
    """``mount(options)``: a tmpfs on tmp_path/disk, unmounted at the end; skipped where mounting is not permitted."""
    where = tmp_path / "disk"
    where.mkdir()
    mounted = []

    def mount(options: str) -> Path:
        proc = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True,
                              text=True)
        if proc.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (needs root): {proc.stderr.strip()}")
        mounted.append(where)
        return where

    try:
        yield mount
    finally:
        for path in mounted:
            subprocess.run(["umount", "-l", str(path)], check=False)  # lazily: a process may still hold it


@pytest.fixture
def pipeline(tmp_path: Path) -> Iterator[Pipeline]:
    """A :class:`~pipeline.Pipeline` in tmp_path on a mesh of its own, nothing started yet; whatever it started is
    stopped at the end (SIGINT, then SIGKILL to what is left)."""
    with Pipeline(tmp_path) as p:
        yield p


@pytest.fixture(scope="session")
def node() -> str:
    """node, with Foxglove's packages of tests/node/package-lock.json installed (npm ci, once)."""
    found = shutil.which("node")
    if found is None:
        why = "node is not installed (Debian: apt install nodejs npm): Foxglove's decoders cannot run"
        if os.environ.get("NWR_REQUIRE_NODE") == "1":
            pytest.fail(why + "; NWR_REQUIRE_NODE=1 requires it")
        pytest.skip(why)
    if not (NODE_DIR / "node_modules" / "@foxglove" / "rosmsg2-serialization").is_dir():
        npm = shutil.which("npm")
        assert npm, "node is installed but npm is not: apt install npm"
        proc = subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=NODE_DIR, capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, f"npm ci in {NODE_DIR} failed: {proc.stderr}"
    return found
