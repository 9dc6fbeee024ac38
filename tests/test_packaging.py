"""The package builds without a warning from its build backend, with its data files."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_the_wheel_builds_without_backend_warnings_and_carries_its_data(tmp_path):
    source = tmp_path / "src"
    source.mkdir()
    shutil.copy(ROOT / "pyproject.toml", source)
    shutil.copy(ROOT / "README.md", source)
    for package in ("common", "services"):
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__"))
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "-v", "--no-deps", "--disable-pip-version-check",
                          "-w", str(tmp_path / "dist"), str(source)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    log = out.stdout + out.stderr
    # Deprecated licence table, data folders that "would be ignored" / are "absent from packages", ...
    warnings = sorted(set(re.findall(r"\w*(?:Backend|Setuptools|Deprecation)Warning: [^\n]*", log)))
    assert not warnings, "\n".join(warnings)
    (wheel,) = (tmp_path / "dist").glob("nwr-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for data in ("nwr/common/profiles/default.toml", "nwr/common/scripts/demo.toml",
                 "nwr/common/robots/ur10e/robot.toml", "nwr/common/robots/ur10e/skin.toml",
                 "nwr/common/robots/ur10e/ur10e.urdf", "nwr/common/study/questionnaire.toml",
                 "nwr/common/robots/fr3/robot.toml", "nwr/common/robots/fr3/skin.toml",
                 "nwr/common/robots/fr3/scripts/demo.toml", "nwr/common/robots/fr3/LICENSE"):
        assert data in names, data
