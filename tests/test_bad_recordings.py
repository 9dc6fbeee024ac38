"""Every command that takes a recording, on the bad files a lab ends up with: one line, never a traceback.

The bad files are made from a short lockstep session: cut off by a crash or a
full disk, killed after its last flushed chunk, only a header, empty, a
directory, another format (JSON, PNG, text), a flipped bit in a chunk or in
the summary, a missing path, a file that cannot be read. Each command is run
in-process through ``nwr.services.cli.main``; two runs of the installed
``nwr`` prove stderr holds one line and no traceback. A live ``nwr replay``
and ``nwr view FILE`` must fail before they start anything.
"""

from __future__ import annotations

import io
import json
import logging
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import msgspec
import pytest
from mcap.records import Chunk, DataEnd
from mcap.stream_reader import StreamReader

from nwr.common.config import Profile
from nwr.common.recordings import RecordingError, read_recording
from nwr.services import cli
from nwr.services.tools.recordings import replay
from nwr.services.view import commands as view_commands

SCRIPT = """
duration_s = 3.0

[[touch]]
pad = "forearm_top"
start_s = 1.0
duration_s = 0.4
peak_hpa = 9.0
"""

# What the one line says, per kind of file (besides the file's name).
EXPECTED = {
    "truncated": ("is not finished", "nwr recover"),
    "unfinished": ("is not finished", "nwr recover"),
    "header-only": ("ends inside its MCAP header", "nothing to read or recover"),
    "garbage-header": ("no MCAP header", "nothing to read or recover"),
    "empty": ("is empty (0 bytes)", "nothing to read or recover"),
    "directory": ("is a directory", "inside.mcap"),
    "json": ("is not an MCAP recording", "JSON"),
    "image": ("is not an MCAP recording", "PNG image"),
    "text": ("is not an MCAP recording", "text file"),
    "bitflip-chunk": ("is damaged", "nwr recover"),
    "bitflip-summary": ("is damaged", "summary", "nwr recover"),
    "missing": ("does not exist",),
    "unreadable": ("permission denied",),
}
# Files nwr info describes and nwr recover rescues (the rest hold nothing to read).
READABLE_DAMAGE = {"truncated", "unfinished", "bitflip-chunk", "bitflip-summary"}
COMMANDS = ["summary", "replay", "replay --fast", "compare BAD GOOD", "compare GOOD BAD", "view", "export"]


def _png() -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00\xff\x00\x00")) + chunk(b"IEND", b""))


def _records(data: bytes) -> list[tuple[int, int, object]]:
    """(offset, end, record) of every top-level record of a valid file."""
    stream = io.BytesIO(data)
    reader = StreamReader(stream, emit_chunks=True).records
    out = []
    while True:
        start = stream.tell()
        try:
            record = next(reader)
        except StopIteration:
            return out
        out.append((start, stream.tell(), record))


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bad")
    script = root / "short.toml"
    script.write_text(SCRIPT)
    base = Profile()
    profile = msgspec.structs.replace(base, recorder=msgspec.structs.replace(base.recorder, chunk_size=16 * 1024))
    good, _simulated, _wall = replay.simulate(profile, str(script), "cartesian", root / "good.mcap")
    data = good.read_bytes()
    records = _records(data)
    chunks = [(start, end) for start, end, record in records if isinstance(record, Chunk)]
    assert len(chunks) >= 3
    data_end = next(start for start, _end, record in records if isinstance(record, DataEnd))

    made: dict[str, Path] = {"good": good}

    def put(kind: str, content: bytes, name: str | None = None) -> None:
        path = root / (name or f"{kind}.mcap")
        path.write_bytes(content)
        made[kind] = path

    middle = (chunks[1][0] + chunks[1][1]) // 2
    put("truncated", data[:middle])  # a crash or a full disk in the middle of a chunk
    put("unfinished", data[:data_end])  # a killed recorder: every chunk flushed, no summary or footer
    put("header-only", data[:20])
    put("garbage-header", b"\x89MCAP0\r\n" + b"\x00" * 40)
    put("empty", b"")
    put("json", json.dumps({"robot": "ur10e", "touches": [1, 2]}).encode())
    put("image", _png(), "image.png")
    put("text", "notes from the lab: participant P07, touch on the forearm (réflexe)\n".encode())
    flipped = bytearray(data)
    flipped[(chunks[1][0] + chunks[1][1]) // 2] ^= 0x10  # inside a chunk's compressed data
    put("bitflip-chunk", bytes(flipped))
    summary = bytearray(data)
    summary[data_end + (len(data) - data_end) // 2] ^= 0x10  # inside the summary (the index)
    put("bitflip-summary", bytes(summary))
    directory = root / "a-directory.mcap"
    directory.mkdir()
    (directory / "inside.mcap").write_bytes(data)
    made["directory"] = directory
    made["missing"] = root / "no-such-file.mcap"
    locked = root / "locked.mcap"
    locked.write_bytes(data)
    locked.chmod(0)
    made["unreadable"] = locked
    (root / "out").mkdir()
    return made


@pytest.fixture
def unreadable(files: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """The locked file cannot be opened, even by root (who ignores its mode)."""
    locked = files["unreadable"]
    real_open = Path.open

    def deny(self: Path, *args: object, **kwargs: object) -> object:
        if self == locked:
            raise PermissionError(13, "Permission denied", str(self))
        return real_open(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "open", deny)


@pytest.fixture
def nothing_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    """A live replay or the view of a file must fail before it starts a process, a session or a server."""
    def refuse(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("started something for a bad recording")

    monkeypatch.setattr(replay, "spawn", refuse)
    monkeypatch.setattr(replay, "Node", refuse)
    monkeypatch.setattr(view_commands, "ViewServer", refuse)


def argv(command: str, bad: Path, good: Path, out: Path) -> list[str]:
    return {
        "info": ["info", str(bad)],
        "recover": ["recover", str(bad), "-o", str(out / f"{bad.stem}-recovered.mcap")],
        "summary": ["summary", str(bad)],
        "replay": ["replay", str(bad), "--reflex", "uniform", "-o", str(out / "live.mcap")],
        "replay --fast": ["replay", str(bad), "--fast", "-o", str(out / "fast.mcap")],
        "compare BAD GOOD": ["compare", str(bad), str(good), "--figure", "none"],
        "compare GOOD BAD": ["compare", str(good), str(bad), "--figure", "none"],
        "view": ["view", str(bad), "--port", "0"],
        "export": ["export", "--foxglove", str(bad), str(out / "export.mcap")],
    }[command]


def run(args: list[str], caplog: pytest.LogCaptureFixture) -> tuple[int, list[str]]:
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        code = cli.main(["--log-level", "WARNING", *args])
    return code, [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]


@pytest.mark.usefixtures("unreadable", "nothing_starts")
@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("kind", sorted(EXPECTED))
def test_one_line_and_exit_2_for_every_bad_file(files: dict[str, Path], kind: str, command: str,
                                                 caplog: pytest.LogCaptureFixture,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    bad, out = files[kind], files["good"].parent / "out"
    code, errors = run(argv(command, bad, files["good"], out), caplog)
    assert code == 2
    assert len(errors) == 1, errors
    assert str(bad) in errors[0] and "\n" not in errors[0]
    for words in EXPECTED[kind]:
        assert words in errors[0], errors[0]
    assert not (out / "export.mcap").exists() and not list(out.glob("*.part"))  # nothing half-written
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.usefixtures("unreadable")
@pytest.mark.parametrize("kind", sorted(EXPECTED))
def test_info_and_recover(files: dict[str, Path], kind: str, caplog: pytest.LogCaptureFixture,
                          capsys: pytest.CaptureFixture[str]) -> None:
    bad, out = files[kind], files["good"].parent / "out"
    info, errors = run(argv("info", bad, files["good"], out), caplog)
    first = capsys.readouterr().out.split("\n", 1)[0]
    recovered = out / f"{bad.stem}-recovered.mcap"
    rescued, recover_errors = run(argv("recover", bad, files["good"], out), caplog)
    if kind in READABLE_DAMAGE:
        # info describes it (exit 1: not intact) and its first line says what to do; recover saves what it can
        assert info == 1 and not errors
        assert str(bad) in first and ("NOT finished" in first or "damaged" in first) and "nwr recover" in first
        assert rescued == 0 and not recover_errors
        records, metadata = read_recording(recovered)
        assert records and "recovery" in metadata
    else:
        for code, lines in ((info, errors), (rescued, recover_errors)):
            assert code == 2 and len(lines) == 1 and str(bad) in lines[0]
            assert all(words in lines[0] for words in EXPECTED[kind]), lines[0]
        assert not recovered.exists()


@pytest.mark.usefixtures("unreadable")
@pytest.mark.parametrize("kind", sorted(EXPECTED))
def test_the_reader_classifies_each_kind(files: dict[str, Path], kind: str) -> None:
    problem = {"truncated": "unfinished", "unfinished": "unfinished", "header-only": "header",
               "garbage-header": "header", "json": "not_mcap", "image": "not_mcap", "text": "not_mcap",
               "bitflip-chunk": "damaged", "bitflip-summary": "damaged"}.get(kind, kind)
    with pytest.raises(RecordingError) as caught:
        read_recording(files[kind])
    assert caught.value.problem == problem


def test_the_good_file_reads_and_info_says_intact(files: dict[str, Path], caplog: pytest.LogCaptureFixture,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    records, metadata = read_recording(files["good"])
    assert records and metadata["session"]["strategy"] == "cartesian"
    assert run(["info", str(files["good"])], caplog) == (0, [])
    assert "intact" in capsys.readouterr().out.split("\n", 1)[0]


def test_outputs_that_cannot_be_written_get_one_line(files: dict[str, Path], caplog: pytest.LogCaptureFixture,
                                                     tmp_path: Path) -> None:
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    target = blocked / "x.mcap"  # under a file: no directory can be made there
    for args in (["recover", str(files["truncated"]), "-o", str(target)],
                 ["export", "--foxglove", str(files["good"]), str(target)],
                 ["replay", str(files["good"]), "--fast", "-o", str(target)]):
        code, errors = run(args, caplog)
        assert code == 2 and len(errors) == 1 and str(target) in errors[0], (args, errors)


def test_replay_refuses_to_overwrite_its_input(files: dict[str, Path], caplog: pytest.LogCaptureFixture) -> None:
    good = files["good"]
    before = good.read_bytes()
    code, errors = run(["replay", str(good), "--fast", "-o", str(good)], caplog)
    assert code == 2 and "is the recording being replayed" in errors[0]
    assert good.read_bytes() == before


def _nwr() -> list[str]:
    installed = Path(sys.executable).with_name("nwr")
    return [str(installed)] if installed.exists() else [sys.executable, "-m", "nwr.services.cli"]


@pytest.mark.parametrize(("kind", "command"), [("truncated", "summary"), ("bitflip-chunk", "replay --fast"),
                                               ("directory", "export")])
def test_the_installed_command_prints_one_line_and_no_traceback(files: dict[str, Path], kind: str,
                                                                command: str) -> None:
    args = argv(command, files[kind], files["good"], files["good"].parent / "out")
    proc = subprocess.run([*_nwr(), "--log-level", "WARNING", *args], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "MPLBACKEND": "Agg"})
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(lines) == 1 and str(files[kind]) in lines[0], proc.stderr
