"""Write the README's example of what `nwr demo` prints, from a real run of it.

    .venv/bin/python scripts/readme_example.py [--profile FILE] [--check]

Runs `nwr demo` (the whole pipeline, about a minute) into a temporary
directory and puts its per-touch table and the lines after it into the
README's block below the marker (the recording's path shown as
`recordings/<session>.mcap`). `--check`: only say whether the README's block
has the run's shape (tests/test_readme.py checks that on every test run,
from the same session in lockstep).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MARKER = "<!-- `nwr demo`'s output: written by scripts/readme_example.py, checked by tests/test_readme.py -->"


def example(stdout: str, recording: Path) -> str:
    """What the README shows of a run's output: from the table on, the recording's path as the README names it."""
    text = stdout.replace(str(recording.with_suffix("")), "recordings/<session>")
    start = text.index("\nRecording ")
    return text[start + 1:].rstrip() + "\n"


def readme_block(readme: str) -> str:
    """The README's example: the fenced block after the marker."""
    after = readme.split(MARKER, 1)[1]
    match = re.match(r"\s*```\n(.*?)```\n", after, re.S)
    if match is None:
        raise ValueError(f"no fenced block after the marker {MARKER!r} in the README")
    return match.group(1)


def replace_block(readme: str, block: str) -> str:
    old = readme_block(readme)
    head, tail = readme.split(MARKER, 1)
    return head + MARKER + tail.replace(old, block, 1)


def run_demo(profile: str | None) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        recording = Path(tmp) / "session.mcap"
        cmd = [sys.executable, "-m", "nwr.services.cli", *(["--profile", profile] if profile else []),
               "demo", "--output", str(recording)]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
        if proc.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
        return example(proc.stdout, recording)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--profile", help="profile for the demo (another base port beside a running pipeline)")
    parser.add_argument("--check", action="store_true", help="compare with the README, do not write it")
    args = parser.parse_args()
    block = run_demo(args.profile)
    readme = README.read_text(encoding="utf-8")
    if args.check:
        sys.path.insert(0, str(ROOT / "tests"))
        from test_readme import shape

        same = shape(block) == shape(readme_block(readme))
        print("the README's example has the shape of this run" if same else
              f"the README's example differs from this run:\n{block}")
        return 0 if same else 1
    README.write_text(replace_block(readme, block), encoding="utf-8")
    print(block, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
