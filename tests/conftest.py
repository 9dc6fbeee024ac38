"""Fixtures shared by several test files."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pipeline import Pipeline


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
