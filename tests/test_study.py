"""The study protocol: three blocks, three conditions, one recording each, switched live."""

from __future__ import annotations

import subprocess
import sys

import pytest

from nwr.common.errors import ConfigError
from nwr.common.recordings import read_recording
from nwr.services.tools.study.main import ORDERS, block_path, conditions_of, order_of


def test_orders_are_a_latin_square():
    for position in range(3):
        assert sorted(order[position] for order in ORDERS) == ["cartesian", "location", "uniform"]
    assert order_of(2) == ("location", "cartesian", "uniform")
    with pytest.raises(ConfigError, match="orders 1 to 3"):
        order_of(4)


def test_other_conditions_are_compared_in_a_latin_square_of_their_own():
    conditions = conditions_of("uniform,cartesian,whole-arm,location")
    square = [order_of(n, conditions) for n in range(1, 5)]
    assert square[0] == ("uniform", "cartesian", "whole-arm", "location")
    for position in range(4):
        assert sorted(order[position] for order in square) == sorted(conditions)
    assert conditions_of(None) == conditions_of("") == ("uniform", "location", "cartesian")
    for bad, why in (("uniform,cartesain", "not a reflex strategy"), ("uniform", "two or more"),
                     ("uniform,uniform", "each once")):
        with pytest.raises(ConfigError, match=why):
            conditions_of(bad)


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.parametrize(("conditions", "order", "port"), [
    (None, 3, 17880),  # the paper's
    ("cartesian,whole-arm", 2, 17890),  # this project's whole-arm withdrawal against CR
])
def test_study_session(tmp_path, conditions, order, port):
    profile = tmp_path / "profile.toml"
    profile.write_text(f'[zenoh]\nbase_port = {port}\n[recorder]\ndirectory = "{tmp_path}"\n')
    proc = subprocess.run(
        [sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "study", "--participant", "P07",
         "--order", str(order), "--block-s", "6", "--follow-target", "1.5",
         *(["--conditions", conditions] if conditions else [])],
        capture_output=True, text=True, timeout=180,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    targets: set[int] = set()
    for block, condition in enumerate(order_of(order, conditions_of(conditions)), start=1):
        records, metadata = read_recording(block_path(tmp_path, "P07", block, condition))
        session = metadata["session"]
        assert (session["label.participant"], session["label.condition"], session["label.block"]) == \
            ("P07", condition, str(block))
        assert session["strategy"] == condition
        states = [r.message for r in records if r.key == "robot/state"]
        assert states and {s.owner for s in states} == {condition}
        executed = {st.reflex.strategy for r in records if r.key.endswith("/status")
                    for st in [r.message] if st.reflex is not None and not st.reflex.shadow}
        assert executed == {condition}  # the simulated participant's touches caused this condition's reflexes
        targets |= {r.message.target_pad for r in records if r.key == f"reflex/{condition}/status"}
    # The target pad moved on after touches. Per block it may not: the simulated participant presses only
    # while the arm does its task, and a loaded machine leaves a 6 s block room for one strong touch.
    assert len(targets) >= 2


def test_the_blocks_table_says_which_recording_is_unreadable_and_lists_the_others(tmp_path, capsys):
    """A recorder killed mid-block leaves an unfinished file: the study's closing table says so for that block
    and still lists the others (it used to end the session with a traceback after every block was stored)."""
    from pathlib import Path

    from nwr.common.config import Profile
    from nwr.services.tools.recordings.replay import simulate
    from nwr.services.tools.study.main import _print_blocks

    good = simulate(Profile(), str(Path(__file__).parent / "data" / "short.toml"), "cartesian",
                    tmp_path / "P01-b1-cartesian.mcap")[0]
    cut = tmp_path / "P01-b2-uniform.mcap"
    cut.write_bytes(Path(good).read_bytes()[:4000])
    _print_blocks([(1, "cartesian", Path(good)), (2, "uniform", cut)], Profile())
    lines = capsys.readouterr().out.splitlines()
    first = next(line for line in lines if line.split()[:2] == ["1", "cartesian"])
    assert int(first.split()[2]) >= 3 and str(good) in first  # its touches
    second = next(line for line in lines if line.split()[:2] == ["2", "uniform"])
    assert "unreadable" in second and str(cut) in second
