"""Small command-line promises: `nwr switch` returns when the bridge refuses, `nwr status` names the protocol it
dials, `nwr recover` removes the dead recorder's space reserve, and help texts are plain text."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import ZenohSection
from nwr.common.recordings import McapRecorder
from nwr.services import cli
from nwr.services.tools import status

PORT = 18150  # away from the default mesh and the other e2e tests


def test_status_names_the_tls_endpoint_it_dials_in_secure_mode() -> None:
    assert status.dialled(ZenohSection(router=["tcp/10.0.0.2:7447"])) == ["tcp/10.0.0.2:7447"]
    secure = ZenohSection(router=["tcp/10.0.0.2:7447"], secure=True)
    assert status.dialled(secure) == ["tls/10.0.0.2:7447"]
    report = status.StatusReport("ur10e", status.dialled(secure), 2.0, [])
    assert status.format_report(report).startswith("robot ur10e via tls/10.0.0.2:7447;")


def damaged_recording(path: Path) -> None:
    """A recording whose recorder was killed: chunks on disk, no summary."""
    f = path.open("wb")
    recorder = McapRecorder(f, "ur10e", chunk_size=512)
    for seq in range(200):
        recorder.write(keys.key("ur10e", keys.diag("gain")),
                       m.Diagnostic(seq=seq, stamp_ns=10**9 + seq, service="gain", level="info", code="x",
                                    message="a diagnostic of some length " * 3, count=1), 10**9 + seq)
    f.flush()
    f.close()  # never finished


def test_recover_removes_the_dead_recorder_s_space_reserve(tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    damaged_recording(path)
    reserve = tmp_path / ".session.mcap.reserve"
    reserve.write_bytes(b"\0" * 4096)
    with path.open("rb"):  # a recorder still writing the session: its reserve stays
        assert cli.main(["recover", str(path), "-o", str(tmp_path / "a.mcap")]) == 0
    assert reserve.exists()
    assert cli.main(["recover", str(path), "-o", str(tmp_path / "b.mcap")]) == 0
    assert not reserve.exists() and (tmp_path / "b.mcap").stat().st_size > 0
    # A split session's part: the reserve is named after the session.
    part = tmp_path / "split-001.mcap"
    damaged_recording(part)
    (tmp_path / ".split.mcap.reserve").write_bytes(b"\0")
    assert cli.main(["recover", str(part), "-o", str(tmp_path / "c.mcap")]) == 0
    assert not (tmp_path / ".split.mcap.reserve").exists()


MARKUP = re.compile(r"``|:(mod|func|class|meth|attr|data|exc):`")


def parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found += parsers(sub)
    return found


def test_help_texts_are_plain_text() -> None:
    everything = parsers(cli.build_parser(None))
    assert len(everything) > 30
    marked = []
    for p in everything:
        texts = [p.description or "", p.epilog or "", *(a.help or "" for a in p._actions)]
        texts += [p.format_help()]
        marked += [f"{p.prog}: {MARKUP.search(t)[0]!r} in {t[:80]!r}" for t in texts if MARKUP.search(t)]
    assert not marked, "\n".join(marked)


@pytest.mark.e2e
def test_switch_to_a_planner_that_is_not_running_returns_when_the_bridge_refuses(tmp_path: Path) -> None:
    profile = tmp_path / "profile.toml"
    profile.write_text(f"[zenoh]\nbase_port = {PORT}\n")
    nwr = [sys.executable, "-m", "nwr.services.cli", "--profile", str(profile)]
    bridge = subprocess.Popen([*nwr, "run", "bridge"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert bridge.stdout is not None
        for line in bridge.stdout:
            if "following planner" in line:
                break
        t0 = time.monotonic()
        proc = subprocess.run([*nwr, "switch", "nosuch"], capture_output=True, text=True, timeout=60)
        took = time.monotonic() - t0
    finally:
        bridge.terminate()
        bridge.communicate(timeout=20)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "the bridge refused: switch to planner 'nosuch' refused: it is not running" in proc.stdout
    assert took < 6.0, f"{took:.1f} s: it waited for its timeout (10 s)"
