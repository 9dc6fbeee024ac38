"""The pipeline's graph is the one description of the layout: the deployment, the access control and the wirings agree.

- ``deploy/compose.yaml`` runs the graph's services with the graph's waits;
- ``deploy/acl.json5`` lets each service put exactly on the keys the key
  registry says it produces;
- each service's wiring writes only keys its service produces, reads what
  its declared inputs say (and the registry does not say it again), and the
  registry's producers and consumers name only known parties;
- imports go downward only: common, services, pipeline, tools, CLI.
"""

from __future__ import annotations

import ast
import fnmatch
import json
import re
from pathlib import Path

import pytest
import yaml

from nwr.common import keys
from nwr.common.node import SLOTS
from nwr.services.bridge.wiring import BridgeWiring
from nwr.services.gain.wiring import GainWiring
from nwr.services.gateway.wiring import GatewayWiring
from nwr.services.pipeline.graph import (
    ROUTER,
    SERVICES,
    START_ORDER,
    WIRINGS,
    Layout,
    Unit,
    process_name,
    reads,
    stop_order,
    units,
    wiring_for,
    writes,
)
from nwr.services.planner import strategies

ROOT = Path(__file__).resolve().parents[1]
# Parties that put or read keys without being a service of the graph (tools).
TOOLS = {"operator", "replay", "status"}



def test_every_service_and_the_router_have_a_place_in_the_start_order() -> None:
    assert set(START_ORDER) == {*SERVICES, ROUTER}
    assert START_ORDER.index("recorder") < min(START_ORDER.index(s) for s in SERVICES if s != "recorder")
    assert START_ORDER[-1] == "gateway"
    assert set(SLOTS) <= set(SERVICES)


def test_the_registry_names_only_known_parties_and_every_key_has_both_ends() -> None:
    known = {*SERVICES, *TOOLS, keys.ANY_SERVICE}
    for topic in keys.TOPICS:
        assert topic.producers and topic.consumers, topic.pattern
        assert topic.pattern in reads("recorder"), topic.pattern
        assert set(topic.producers) <= known and set(topic.consumers) <= known, topic.pattern
        assert "recorder" in topic.consumers, f"{topic.pattern} would not be recorded"
    assert "skin/pain" in reads("planner") and "skin/pain" in reads("bridge")
    assert writes("gain") == ("skin/pain", "diag/*", "journal/*")
    assert writes("recorder") == ("diag/*",)


def test_what_a_wired_service_reads_is_its_declared_inputs_and_written_nowhere_else() -> None:
    for service in WIRINGS:
        wiring = wiring_for(service)
        declared = [inp.key for inp in wiring.inputs.values() if inp.key is not None]
        assert declared and reads(service) == tuple(dict.fromkeys(declared)), service
        for topic in keys.TOPICS:  # the registry's consumers are the parties without a wiring
            assert service not in topic.consumers, (service, topic.pattern)
        for inp in wiring.inputs.values():
            assert inp.key is None or keys.topic_for(inp.key.replace("*", "x")).pattern == inp.key, inp
            assert callable(getattr(wiring, inp.method)), inp
    assert wiring_for("planner-lab") is wiring_for("planner")
    assert reads("bridge") == ("robot/command/*", "skin/pressure", "skin/pain", "skin/touch", "control/active",
                               "control/safety")
    assert "world/skin" in reads("gateway")  # a physics world's skin, from the bridge that hosts it


def test_each_wiring_writes_only_what_its_service_produces() -> None:
    for service, wiring in (("gateway", GatewayWiring), ("gain", GainWiring), ("bridge", BridgeWiring)):
        assert set(wiring.outputs) <= set(writes(service)), service
    # A planner's keys carry its name: its wiring builds them (robot/command/<name>, reflex/<name>/...).
    for pattern in ("robot/command/*", "reflex/*/status", "reflex/*/decision"):
        assert pattern in writes("planner")


def test_a_launch_starts_in_the_graphs_order_and_the_gateway_waits_for_the_others() -> None:
    layout = Layout(planners=["uniform", "cartesian"], active="cartesian", recorder=["--output", "x.mcap"],
                    view_port=8765, gateway=["--script", "demo"])
    got = units(layout)
    assert [u.label for u in got] == ["recorder", "bridge", "planner-uniform", "planner-cartesian", "gain", "view",
                                      "gateway"]
    assert got[1] == Unit("bridge", "bridge", ("--active", "cartesian"))
    gateway = got[-1]
    assert gateway.args[:2] == ("--wait-for", "recorder,bridge,planner-uniform,planner-cartesian,gain")
    assert gateway.args[2:] == ("--script", "demo")
    assert got[0].command() == ["run", "recorder", "--output", "x.mcap"]


def test_an_unnamed_planner_is_waited_for_under_the_profiles_name() -> None:
    got = units(Layout(planner_name="lab", recorder=None))
    assert [u.label for u in got] == ["bridge", "planner", "gain", "gateway"]
    assert got[-1].args[:2] == ("--wait-for", "bridge,planner-lab,gain")


@pytest.mark.parametrize(
    ("argv", "bridge", "error"),
    [
        ([], ("--active", "cartesian"), None),
        (["--backend", "sim"], ("--active", "cartesian", "--backend", "sim"), None),
        (["--backend", "ur_rtde", "--robot-ip", "192.0.2.10", "--i-am-next-to-the-robot"],
         ("--active", "cartesian", "--backend", "ur_rtde", "--robot-ip", "192.0.2.10", "--i-am-next-to-the-robot"),
         None),
        (["--backend", "ur_rtde", "--i-am-next-to-the-robot"], None, "--robot-ip"),
        (["--backend", "ur_rtde", "--robot-ip", "192.0.2.10"], None, "--i-am-next-to-the-robot"),
        (["--robot-ip", "192.0.2.10", "--i-am-next-to-the-robot"], None, "for a real arm.s backend"),
    ],
)
def test_up_and_demo_hand_the_arms_flags_to_the_bridge_or_refuse_before_anything_starts(
        argv: list[str], bridge: tuple[str, ...] | None, error: str | None) -> None:
    from nwr.common.config import Profile
    from nwr.common.errors import ConfigError
    from nwr.services.cli import build_parser
    from nwr.services.tools.demo import layout_for

    for command in ("up", "demo"):
        args = build_parser().parse_args([command, "--reflex", "cartesian", *argv])
        if error is not None:
            with pytest.raises(ConfigError, match=error):
                layout_for(args, Profile(), None)
            continue
        unit = next(u for u in units(layout_for(args, Profile(), None)) if u.service == "bridge")
        # `nwr demo` with no backend runs its default world, the physics world: the bridge hosts it.
        assert unit.args == ((*bridge, "--backend", "physics") if command == "demo" and not argv else bridge)


def test_stop_order_bridge_first_then_gateway_recorder_after_the_others_router_last() -> None:
    labels = [u.label for u in units(Layout(active="uniform", recorder=[], router=["--listen", "tcp/127.0.0.1:1"]))]
    assert labels == ["router", "recorder", "bridge", "planner-uniform", "gain", "gateway"]
    assert stop_order(labels) == [["bridge"], ["gateway"], ["gain", "planner-uniform"], ["recorder"], ["router"]]
    assert stop_order(["bridge", "gain"]) == [["bridge"], ["gain"]]
    assert units(Layout(active="x", router=[]))[0].command() == ["router"]


def _expand(text: str) -> str:
    """Compose's ${VAR:-default} -> default."""
    return re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", text)


def test_compose_runs_the_graphs_services_with_its_waits() -> None:
    compose = yaml.safe_load((ROOT / "deploy" / "compose.yaml").read_text())["services"]
    # The services every `up` starts (those under a compose profile are opt-in).
    default = {name: _expand(s["command"]).split() for name, s in compose.items()
               if "profiles" not in s and isinstance(s["command"], str) and s["command"].startswith("run ")}
    active = default["planner"][default["planner"].index("--name") + 1]
    expected = units(Layout(active=active, recorder=[]))
    assert sorted(cmd[1] for cmd in default.values()) == sorted(u.service for u in expected)
    assert default["bridge"][2:4] == ["--active", active]
    waits = default["gateway"][default["gateway"].index("--wait-for") + 1]
    assert waits == expected[-1].args[1]
    assert compose["router"]["command"][0] == ROUTER
    # Every service (opt-in ones too) is a service of the graph.
    for name, s in compose.items():
        if isinstance(s["command"], str) and s["command"].startswith("run "):
            assert s["command"].split()[1] in SERVICES, name


def _acl() -> dict[str, list[str]]:
    """deploy/acl.json5 -> subject -> the key expressions it may put on (relative to nwr/<robot>/)."""
    text = (ROOT / "deploy" / "acl.json5").read_text()
    text = re.sub(r"^\s*//.*$", "", text, flags=re.M)
    text = re.sub(r"([{,\s])([A-Za-z_]+):", r'\1"\2":', text)
    text = re.sub(r",(\s*[}\]])", r"\1", text)
    acl = json.loads(text)
    rules = {r["id"]: r for r in acl["rules"]}
    puts: dict[str, list[str]] = {}
    for policy in acl["policies"]:
        for subject in policy["subjects"]:
            for rule in (rules[r] for r in policy["rules"]):
                if "put" in rule["messages"] and "ingress" in rule["flows"] and rule["key_exprs"] != ["nwr/**"]:
                    puts.setdefault(subject, []).extend(k.removeprefix("nwr/*/") for k in rule["key_exprs"])
    return puts


def _instances(service: str, name: str) -> set[str]:
    """The concrete keys a process ``name`` of ``service`` may put on, from the registry."""
    out = set()
    for pattern in writes(service):
        if pattern in ("diag/*", "journal/*"):
            out.add(pattern.replace("*", name))
        elif service == "planner" and pattern.startswith("reflex/"):
            out.add(f"reflex/{name.removeprefix(keys.PLANNER_SERVICE_PREFIX)}/*")
        elif service == "planner":
            out.add(pattern.replace("*", name.removeprefix(keys.PLANNER_SERVICE_PREFIX)))
        else:
            out.add(pattern)
    return out


@pytest.mark.parametrize("service", ["gateway", "gain", "bridge", "recorder", "view", "planner"])
def test_the_access_control_lets_each_service_put_exactly_what_the_registry_says(service: str) -> None:
    acl = _acl()
    names = [process_name("planner", s) for s in strategies.names()] if service == "planner" else [service]
    for name in names:
        allowed = set(acl.get(name, []))
        expected = _instances(service, name)
        if service in ("recorder", "view"):
            expected -= {f"journal/{name}"}  # they journal nothing: no wiring
        # Journals only for the services with a wiring.
        assert allowed == expected, name


def test_the_operator_may_switch_and_nothing_else_moves_the_arm() -> None:
    acl = _acl()
    assert "control/active" in acl["operator"] and "control/safety" in acl["operator"]
    producers = {t.pattern: t.producers for t in keys.TOPICS}
    assert producers["control/active"] == producers["control/safety"] == ("operator",)
    assert not any(fnmatch.fnmatchcase(k, "robot/command/*") for k in acl["operator"])


# ------------------------------------------------------------------------------ layering

LAYERS = ("common", "services", "pipeline", "tools", "cli")


def _layer(module: str) -> int | None:
    """The layer of an ``nwr.`` module, or None for anything else."""
    parts = module.split(".")
    if parts[0] != "nwr" or len(parts) < 2:
        return None
    if parts[1] == "common":
        return 0
    if parts[1] != "services":
        return None
    name = parts[2] if len(parts) > 2 else ""
    return {"pipeline": 2, "tools": 3, "cli": 4}.get(name, 1)


def _modules() -> list[tuple[str, Path]]:
    out = []
    for top in ("common", "services"):
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            out.append((".".join(["nwr", *rel.parts]).removesuffix(".__init__"), path))
    return out


def _imports(path: Path, module: str) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):  # lazy imports inside functions too
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the package
                base = module.split(".")[: -node.level]
                target = ".".join([*base, node.module] if node.module else base)
            else:
                target = node.module or ""
            found += [target] + [f"{target}.{alias.name}" for alias in node.names]
    return found


def test_imports_only_go_downward() -> None:
    upward = []
    for module, path in _modules():
        own = _layer(module)
        assert own is not None, module
        for target in _imports(path, module):
            layer = _layer(target)
            if layer is not None and layer > own and _is_module(target):
                upward.append(f"{module} ({LAYERS[own]}) imports {target} ({LAYERS[layer]})")
    assert not upward, "\n".join(upward)


def _is_module(name: str) -> bool:
    rel = Path(*name.split(".")[1:])
    return (ROOT / rel).with_suffix(".py").exists() or (ROOT / rel).is_dir()


def test_the_layering_check_sees_an_upward_import(tmp_path: Path) -> None:
    bad = tmp_path / "m.py"
    bad.write_text("def f():\n    from nwr.services.tools.recordings import replay\n")
    assert "nwr.services.tools.recordings.replay" in _imports(bad, "nwr.common.m")
    assert _layer("nwr.services.tools.recordings.replay") == 3 and _layer("nwr.common.keys") == 0
    assert _layer("nwr.services.bridge.core") == 1 and _layer("nwr.services.pipeline.lockstep") == 2


def test_every_package_is_installed() -> None:
    """The image installs the wheel, not the checkout: a package missing from pyproject.toml is missing there."""
    import tomllib

    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(setuptools["packages"])
    found = {".".join(["nwr", *p.parent.relative_to(ROOT).parts])
             for top in ("common", "services") for p in (ROOT / top).rglob("__init__.py")}
    # Besides the code, the folders of data files (profiles, scripts, a robot's files), each with its files.
    data = set(setuptools["package-data"])
    assert found | data == listed and not found & data


def test_each_planners_log_lines_carry_its_name_when_several_run() -> None:
    from nwr.services.cli import build_parser, log_label

    parser = build_parser()
    assert log_label(parser.parse_args(["run", "planner", "--name", "uniform", "--reflex", "uniform"])) == \
        "planner-uniform"
    assert log_label(parser.parse_args(["run", "planner", "--reflex", "whole-arm"])) == "planner-whole-arm"
    assert log_label(parser.parse_args(["run", "planner"])) == "planner"
    assert log_label(parser.parse_args(["run", "bridge"])) == "bridge"
    assert log_label(parser.parse_args(["demo"])) == "demo"


def test_a_routers_clients_start_once_it_listens_and_not_on_a_router_that_died() -> None:
    import socket
    import subprocess
    import sys

    from nwr.common.errors import NwrError
    from nwr.services.pipeline.graph import ROUTER, Unit
    from nwr.services.pipeline.supervisor import listen_endpoint, wait_for_router, wait_listening

    assert listen_endpoint(Unit(ROUTER, ROUTER, ("--listen", "tls/10.0.0.2:7447", "--acl", "a.json5"))) == \
        "tls/10.0.0.2:7447"
    assert listen_endpoint(Unit(ROUTER, ROUTER, ())) is None
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        with socket.socket() as server:
            server.bind(("127.0.0.1", 0))
            server.listen()
            port = server.getsockname()[1]
            wait_for_router(Unit(ROUTER, ROUTER, ("--listen", f"tcp/127.0.0.1:{port}")), alive)  # returns
        with pytest.raises(NwrError, match="did not listen"):
            wait_listening(f"tcp/127.0.0.1:{port}", alive, timeout_s=0.3)
    finally:
        alive.kill()
        alive.wait()
    with pytest.raises(NwrError, match="exited"):
        wait_listening(f"tcp/127.0.0.1:{port}", alive)


def test_a_journal_entry_of_an_input_no_wiring_declares_is_refused_by_name() -> None:
    from nwr.common import messages as m
    from nwr.common.clock import ManualClock
    from nwr.common.config import Profile
    from nwr.common.journal import Untracked
    from nwr.services.wiring import no_diag

    wiring = wiring_for("gain")(Profile(), journal=Untracked(ManualClock()), out=lambda k, msg: None, diag=no_diag)
    with pytest.raises(ValueError, match="no input 'tock'.*pressure"):
        wiring.replay(m.JournalEntry("tock"), None)


@pytest.mark.parametrize("service", sorted(SERVICES))
def test_a_service_process_loads_its_own_code_and_no_tool(service: str) -> None:
    # In a fresh interpreter: this one has imported every tool for other tests.
    import subprocess
    import sys

    code = ("import sys\nfrom nwr.services import cli\n"
            f"try:\n    cli.main(['--profile', 'default', 'run', {service!r}, '--help'])\n"
            "except SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith('nwr.services.')))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    loaded = proc.stdout.strip().splitlines()[-1]
    assert "nwr.services.tools" not in loaded, loaded
    others = {s for s in SERVICES if s != service}
    assert not [s for s in others if f"'nwr.services.{s}." in loaded], loaded


def test_no_import_cycles() -> None:
    import graphlib

    modules = dict(_modules())
    graph = {module: {t for t in _imports(path, module) if t in modules and t != module}
             for module, path in modules.items()}
    try:
        list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"an import cycle (lazy imports inside functions included): {' -> '.join(exc.args[1])}")
