"""The compose deployment, built by the offline path and run for real; the online build from a clean clone.

Builds the base image (debootstrap), the wheelhouse and the project image
with deploy/offline/build.sh (the first two are cached per machine), brings
deploy/compose.yaml up on a bridge network as it ships, secure by default
(the certs step makes the lab CA and a certificate per service; the router
takes mutual TLS only and enforces the access control; every service in its
own container, a client of the router container; the router published on
loopback, every container's log rotated), tries intruders without a
certificate and with another CA's, plays a touch script, stops and restarts
the active planner, and checks all of it from the recording the recorder
wrote to its volume.

The online form (deploy/README.md, "With internet") is built from what a
clean clone holds, with the package index: see test_online_build_from_a_clean_clone.

Skipped when no Docker daemon (or no compose) is available, unless
NWR_REQUIRE_DOCKER=1 (set by .ci/run), where that is a failure.
"""

from __future__ import annotations

import collections
import json
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from nwr.common.config import GainSection
from nwr.common.launch import load_script
from nwr.common.recordings import read_recording
from nwr.common.robot import load_description
from nwr.services.gain.core import GainEstimator
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.summary import print_summary

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.docker]

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "data" / "short.toml"
PLANNER = "cartesian"
SERVICES = ["router", "bridge", "planner", "gain", "recorder", "gateway"]
RECORDING = "compose-test.mcap"
BUILD_SH = ROOT / "deploy" / "offline" / "build.sh"


def _run(cmd: list[str], timeout: float = 600, check: bool = True, **kw: object) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)  # type: ignore[call-overload]
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    return proc


def _docker_setup() -> tuple[list[str] | None, str]:
    """The compose command, or None and why the test cannot run."""
    if shutil.which("docker") is None:
        return None, "no docker client (CI installs Debian's docker.io: see .ci/run)"
    if subprocess.run(["docker", "info"], capture_output=True, timeout=30).returncode != 0:
        return None, "no Docker daemon answers (start dockerd, or run .ci/run)"
    if subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=30).returncode == 0:
        compose = ["docker", "compose"]
    elif shutil.which("docker-compose"):
        compose = ["docker-compose"]
    else:
        return None, "no compose implementation (apt-get install docker-compose)"
    # The base image is built once per machine, by debootstrap, as root.
    base = _run(["bash", str(ROOT / "deploy" / "offline" / "build.sh"), "base-tag"]).stdout.strip()
    if subprocess.run(["docker", "image", "inspect", base], capture_output=True, timeout=30).returncode != 0:
        if os.geteuid() != 0:
            return None, (f"the base image {base} is not built yet and debootstrap needs root: "
                          "sudo deploy/offline/build.sh base")
        if shutil.which("debootstrap") is None:
            return None, "no debootstrap to build the base image (apt-get install debootstrap)"
    return compose, ""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Stages:
    """Wall time of each stage, printed at the end whatever happens."""

    def __init__(self) -> None:
        self.rows: list[tuple[str, float, str]] = []
        self._t = time.monotonic()

    def done(self, name: str, note: str = "") -> None:
        now = time.monotonic()
        self.rows.append((name, now - self._t, note))
        self._t = now

    def format(self) -> str:
        total = sum(r[1] for r in self.rows)
        lines = [f"  {name:<28s} {dt:7.1f} s  {note}" for name, dt, note in self.rows]
        return "compose test stages:\n" + "\n".join(lines) + f"\n  {'total':<28s} {total:7.1f} s"


class Deployment:
    def __init__(self, compose: list[str], project: str, files: list[Path], env: dict[str, str]) -> None:
        self.cmd = [*compose, "-p", project, *[a for f in files for a in ("-f", str(f))]]
        self.project = project
        self.env = env

    def __call__(self, *args: str, timeout: float = 300, check: bool = True) -> subprocess.CompletedProcess[str]:
        return _run([*self.cmd, *args], timeout=timeout, check=check, env=self.env)

    def container(self, service: str) -> str:
        cid = self("ps", "-q", service).stdout.strip()
        assert cid, f"no container for {service}"
        return cid

    def health(self, service: str) -> str:
        return _run(["docker", "inspect", "-f", "{{if .State.Health}}{{.State.Health.Status}}{{else}}{{.State.Status}}"
                     "{{end}}", self.container(service)]).stdout.strip()

    def wait_healthy(self, services: list[str], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        states: dict[str, str] = {}
        while time.monotonic() < deadline:
            states = {s: self.health(s) for s in services}
            if all(v == "healthy" for v in states.values()):
                return
            time.sleep(1.0)
        raise AssertionError(f"not healthy within {timeout_s:.0f} s: {states}\n{self.logs()}")

    def logs(self, tail: int = 40) -> str:
        return self("logs", "--no-color", "--tail", str(tail), check=False).stdout

    def wait_log(self, service: str, text: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            proc = _run(["docker", "logs", self.container(service)], check=False)
            if text in proc.stdout + proc.stderr:
                return
            time.sleep(0.5)
        raise AssertionError(f"{service} did not log {text!r} within {timeout_s:.0f} s\n{self.logs()}")


@pytest.fixture(scope="module")
def compose() -> list[str]:
    cmd, reason = _docker_setup()
    if cmd is None:
        if os.environ.get("NWR_REQUIRE_DOCKER") == "1":
            pytest.fail(f"NWR_REQUIRE_DOCKER=1 but {reason}")
        pytest.skip(reason)
    return cmd


@pytest.fixture()
def deployment(compose: list[str], tmp_path: Path) -> Iterator[tuple[Deployment, Stages]]:
    stages = Stages()
    build = _run(["bash", str(ROOT / "deploy" / "offline" / "build.sh")], timeout=1800)
    for line in build.stdout.splitlines():
        if line.startswith("STAGE "):
            _, name, rest = line.split(" ", 2)
            seconds, _, note = rest.partition(" s")
            stages.rows.append((f"build: {name}", float(seconds), note.strip()))
    stages._t = time.monotonic()
    override = tmp_path / "compose.test.yaml"
    # The script is mounted from tests/data; the recorder writes a fixed name;
    # the gateway's clock starts once the recorder is there too.
    override.write_text(f"""
services:
  gateway:
    command: >-
      run gateway --wait-for bridge,gain,recorder,planner-{PLANNER} --script /etc/nwr-test/{SCRIPT.name}
    volumes:
      - {SCRIPT.parent}:/etc/nwr-test:ro
  recorder:
    command: run recorder --session compose-test --output recordings/{RECORDING}
""")
    # The router is published where compose.yaml publishes it by default (loopback).
    env = {**os.environ, "NWR_PLANNER": PLANNER,
           "NWR_ROUTER_PORT": str(_free_port()), "NWR_IMAGE": os.environ.get("NWR_IMAGE", "nwr:latest"),
           "NWR_CERTS": str(tmp_path / "certs")}
    for name in ("NWR_ROUTER", "NWR_RECORDINGS", "NWR_INSECURE", "NWR_ROUTER_SANS", "NWR_ROUTER_PUBLISH",
                 "NWR_LOG_MAX_SIZE", "NWR_LOG_MAX_FILE"):
        env.pop(name, None)
    project = f"nwrtest{os.getpid()}"
    dep = Deployment(compose, project, [ROOT / "deploy" / "compose.yaml", override], env)
    try:
        yield dep, stages
    finally:
        dep("down", "-v", "--remove-orphans", "-t", "10", check=False)
        stages.done("down -v")
        print(stages.format())


def test_compose_deployment(deployment: tuple[Deployment, Stages], tmp_path: Path,
                            capsys: pytest.CaptureFixture[str]) -> None:
    dep, stages = deployment
    script = load_script(str(SCRIPT))
    dep("up", "-d", "--no-build")
    stages.done("up -d")
    dep.wait_healthy(SERVICES, timeout_s=120)
    # Every service is in its own container with its own address.
    addresses = {s: _run(["docker", "inspect", "-f", "{{range .NetworkSettings.Networks}}{{.IPAddress}}{{end}}",
                          dep.container(s)]).stdout.strip() for s in SERVICES}
    assert len(set(addresses.values())) == len(SERVICES), addresses
    stages.done("healthy (liveliness checks)", ", ".join(f"{s} {a}" for s, a in addresses.items()))
    _check_published_and_rotated(dep)
    _check_secure(dep, tmp_path)
    stages.done("secure: certificates, intruders, operator")

    dep.wait_log("gateway", "touch script", timeout_s=60)
    time.sleep(script.duration_s + 2.0)
    status = _run(["docker", "exec", dep.container("recorder"), "python", "-m", "nwr.services.tools.status"]).stdout
    for service in ("bridge", "gain", "gateway", f"planner-{PLANNER}", "recorder", "router"):
        assert service in status, status
    stages.done("scripted session", f"{script.duration_s:g} s script")

    # The active planner goes away: the bridge must bring the arm to rest.
    t_stop = time.monotonic_ns()
    dep("stop", "-t", "10", "planner")
    time.sleep(3.0)
    t_start = time.monotonic_ns()
    dep("start", "planner")
    # Docker's first health check comes an interval after the start: ask
    # the router directly (the same check) instead of waiting for it.
    deadline = time.monotonic() + 60
    while _run(["docker", "exec", dep.container("recorder"), "python", "-m", "nwr.services.tools.status", "--check",
                f"planner-{PLANNER}", "--timeout", "1"], check=False).returncode != 0:
        assert time.monotonic() < deadline, f"planner did not come back within 60 s\n{dep.logs()}"
    time.sleep(4.0)
    t_end = time.monotonic_ns()
    stages.done("planner stopped, restarted")

    dep("stop", "-t", "20", "recorder")  # finishes the MCAP file
    local = tmp_path / RECORDING
    _run(["docker", "cp", f"{dep.container('recorder')}:/data/recordings/{RECORDING}", str(local)])
    records, metadata = read_recording(local)
    stages.done("recording copied from the volume", f"{len(records)} messages")
    with capsys.disabled():
        print(f"\n{status}")
        assert print_summary(local, str(SCRIPT)) == 0
    _check_session(records, script)
    # Containers share the host's kernel, hence its monotonic clock: the
    # test's own instants delimit the phases in the recording's stamps.
    _check_planner_lost(records, t_stop, t_start)
    _check_resumed(records, t_start, t_end)
    assert metadata["session"]["robot"] == "ur10e"


def _check_published_and_rotated(dep: Deployment) -> None:
    """The router's port on the host's loopback only, and every container's log (certs step included) rotated."""
    bindings = json.loads(_run(["docker", "inspect", "-f", "{{json .HostConfig.PortBindings}}",
                                dep.container("router")]).stdout)
    assert [(b["HostIp"], b["HostPort"]) for b in bindings["7447/tcp"]] == [("127.0.0.1", dep.env["NWR_ROUTER_PORT"])]
    ids = _run(["docker", "ps", "-aq", "--filter", f"label=com.docker.compose.project={dep.project}"]).stdout.split()
    configs: dict[str, object] = {}
    for cid in ids:
        name, config = _run(["docker", "inspect", "-f", "{{index .Config.Labels \"com.docker.compose.service\"}} "
                             "{{json .HostConfig.LogConfig}}", cid]).stdout.strip().split(" ", 1)
        configs[name] = json.loads(config)
    assert set(configs) >= {"certs", *SERVICES}, configs
    for name, config in configs.items():
        assert config == {"Type": "local", "Config": {"max-size": "10m", "max-file": "5"}}, (name, config)
    # `docker compose logs` still reads them.
    assert "Zenoh router" in dep("logs", "--no-color", "router").stdout
    print("router published on 127.0.0.1 only; logs rotated (local, 10m x 5) for " + ", ".join(sorted(configs)))


def _check_secure(dep: Deployment, tmp_path: Path) -> None:
    """The deployment as shipped is secure: its certificates, two intruders refused, the operator's tools work."""
    root = Path(dep.env["NWR_CERTS"])
    assert (root / "ca" / "ca.key").exists()
    assert [p for p in root.rglob("ca.key")] == [root / "ca" / "ca.key"], "the CA key left its directory"
    for service in SERVICES:
        cert = "cartesian" if service == "planner" else service
        assert (root / service / f"{cert}.key").stat().st_mode & 0o077 == 0
        if service != "router":
            proc = _run(["docker", "logs", dep.container(service)], check=False)
            role = "planner" if service == "planner" else service
            assert f"secure mode: mutual TLS to tls/router:7447 as {role}:{cert}" in proc.stdout + proc.stderr, service
    image = dep.env["NWR_IMAGE"]
    network = f"{dep.project}_nwr"
    probe = ["status", "--check", "bridge", "--timeout", "3"]
    # No certificate at all (plain TCP to the TLS port).
    plain = _run(["docker", "run", "--rm", "--network", network, "-e", "NWR_ROUTER=tcp/router:7447",
                  "-e", "NWR_INSECURE=1", image, *probe], check=False, timeout=120)
    assert plain.returncode != 0 and "cannot open a Zenoh session" in plain.stderr, plain
    # A certificate from another CA, while trusting the lab's CA (so the router is the one refusing).
    other = tmp_path / "other-ca"
    _run(["docker", "run", "--rm", "--network", "none", "--user", "0:0", "-v", f"{other}:/certs", image,
          "certs", "provision", "/certs", "--owner", "10001:10001", "operator=operator:operator"], timeout=120)
    shutil.copy(root / "operator" / "ca.crt", other / "operator" / "lab-ca.crt")
    foreign = _run(["docker", "run", "--rm", "--network", network, "-v", f"{other / 'operator'}:/certs:ro",
                    "-e", "NWR_ROUTER=tcp/router:7447", "-e", "NWR_TLS_CA=/certs/lab-ca.crt",
                    "-e", "NWR_TLS_CERT=/certs/operator.crt", "-e", "NWR_TLS_KEY=/certs/operator.key",
                    image, *probe], check=False, timeout=120)
    assert foreign.returncode != 0 and "cannot open a Zenoh session" in foreign.stderr, foreign
    # The operator's tools, with the lab's operator certificate.
    status = dep("run", "--rm", "operator", "status", "--check", "bridge", "--timeout", "5", timeout=120, check=False)
    assert status.returncode == 0, status
    # The reduced mode: the operator's alone. The view's certificate (a service of the lab's own) may not.
    view = _run(["docker", "run", "--rm", "--network", network, "-v", f"{root / 'view'}:/certs:ro",
                 "-e", "NWR_ROUTER=tls/router:7447", "-e", "NWR_TLS_CA=/certs/ca.crt",
                 "-e", "NWR_TLS_CERT=/certs/view.crt", "-e", "NWR_TLS_KEY=/certs/view.key",
                 image, "safety", "reduced", "--timeout", "3"], check=False, timeout=120)
    assert view.returncode != 0 and "it is in normal" in view.stdout, view
    for mode in ("reduced", "normal"):
        switched = dep("run", "--rm", "operator", "safety", mode, "--timeout", "10", timeout=120, check=False)
        assert switched.returncode == 0 and f"safety mode: {mode}" in switched.stdout, switched
    print(f"intruders refused: plain TCP ({plain.returncode}), another CA ({foreign.returncode}); "
          "operator ok, its reduced mode too (refused to the view's certificate)")


def _check_session(records: list, script) -> None:  # type: ignore[no-untyped-def]
    desc = load_description()
    touches = analysis.summarize(records, desc)
    estimator = GainEstimator(GainSection(), desc.pads)
    assert len(touches) >= len(script.touch), touches
    latencies: list[float] = []
    resumed: list[str] = []
    for scripted in script.touch:
        touch = next(t for t in touches if t.name == scripted.pad)
        _, gain = estimator.gain(touch.pad, scripted.peak_hpa)
        if gain > 0:
            assert touch.reflex_seq > 0, touch
            assert touch.onset_latency_ms is not None and 0 < touch.onset_latency_ms < 1000, touch
            # Back on the task: 2.4-2.8 s for this script in lockstep and live, loaded or not; once 6.6 s in
            # compose on a loaded CI machine. The bound catches a return that never ends, not a slow one.
            assert touch.resumed_after_s is not None and touch.resumed_after_s < 15.0, touch
            latencies.append(touch.onset_latency_ms)
            resumed.append(_resumption(records, touch))
        else:
            assert touch.reflex_seq == 0, touch
    assert latencies
    print(f"reflex onset across containers: {', '.join(f'{x:.2f}' for x in latencies)} ms "
          f"(median {np.median(latencies):.2f} ms)")
    print("back on the task after:\n  " + "\n  ".join(resumed))


def _resumption(records: list, touch) -> str:  # type: ignore[no-untyped-def]
    """How long the touch's reflex took to give the arm back to the task, with what the bridge reported meanwhile."""
    t0 = touch.start_ns
    t1 = t0 + round((touch.resumed_after_s or 0.0) * 1e9)
    states = collections.Counter(r.message.status for r in records
                                 if r.key == "robot/state" and t0 <= r.message.stamp_ns <= t1)
    modes = [r.message.mode for r in records if r.key.startswith("reflex/") and r.key.endswith("/status")
             and t0 <= r.message.stamp_ns <= t1 and r.message.active]
    changes = [mode for i, mode in enumerate(modes) if i == 0 or modes[i - 1] != mode]
    return (f"{touch.name}: {touch.resumed_after_s:.2f} s; bridge {dict(states)}; "
            f"active planner {' > '.join(map(str, changes))}")


def _check_planner_lost(records: list, t_stop: int, t_start: int) -> None:  # type: ignore[no-untyped-def]
    states = [r.message for r in records if r.key == "robot/state" and t_stop <= r.message.stamp_ns <= t_start]
    assert states, "no robot/state while the planner was stopped"
    statuses = {s.status for s in states}
    assert statuses & {"planner_lost", "stale_command"}, statuses
    # At rest well before the planner came back.
    tail = [s for s in states if s.stamp_ns >= t_start - 1_000_000_000]
    assert tail and max(max(abs(v) for v in s.dq) for s in tail) < 1e-3, tail[-1]


def _check_resumed(records: list, t_start: int, t_end: int) -> None:  # type: ignore[no-untyped-def]
    status = [r.message for r in records
              if r.key == f"reflex/{PLANNER}/status" and t_start <= r.message.stamp_ns <= t_end]
    task = [s for s in status if s.mode == "TASK"]
    assert task and task[-1].task_time_s > task[0].task_time_s + 1.0, status[-3:]
    states = [r.message for r in records if r.key == "robot/state" and t_start <= r.message.stamp_ns <= t_end]
    moving = [s for s in states if s.status == "ok" and s.owner == PLANNER and max(abs(v) for v in s.dq) > 1e-3]
    assert moving, {s.status for s in states}


def test_every_service_logs_rotated_and_the_router_published_on_loopback() -> None:
    """compose.yaml as written (no Docker needed): one rotated logging anchor for every service, profiles included."""
    text = (ROOT / "deploy" / "compose.yaml").read_text()
    doc = yaml.safe_load(text)
    logging = doc["x-logging"]
    assert logging["driver"] in ("local", "json-file"), logging
    assert set(logging["options"]) >= {"max-size", "max-file"}, logging
    assert {name: s.get("logging") for name, s in doc["services"].items()} == dict.fromkeys(doc["services"], logging)
    assert text.count("logging: *logging") == 2  # the certs step and the anchor every other service merges
    assert doc["services"]["router"]["ports"] == ["${NWR_ROUTER_PUBLISH:-127.0.0.1}:${NWR_ROUTER_PORT:-7447}:7447"]
    assert doc["services"]["view"]["ports"] == ["${NWR_VIEW_PUBLISH:-127.0.0.1}:${NWR_VIEW_PORT:-8765}:8765"]
    assert all("ports" not in s for name, s in doc["services"].items() if name not in ("router", "view"))


# What pip inside the stand-in base trusts: this machine's CA bundle (it may
# reach the index through a TLS-inspecting proxy whose CA only the host knows).
CA_BUNDLES = ("PIP_CERT", "SSL_CERT_FILE", "REQUESTS_CA_BUNDLE")
PROXY_ARGS = ("HTTP_PROXY", "HTTPS_PROXY", "NO_PROXY", "http_proxy", "https_proxy", "no_proxy")


def _clean_context(dest: Path) -> list[str]:
    """What a clean clone of the working tree, committed as it is, holds: tracked and new files, never ignored ones.

    In CI (a fresh clone) that is the clone itself; on a developer's machine
    it leaves out what git ignores (a wheelhouse's wheels, certificates, the
    venv), which a clone would not have either.
    """
    listed = _run(["git", "-C", str(ROOT), "ls-files", "-z", "--cached", "--others", "--exclude-standard"]).stdout
    files = [f for f in listed.split("\0") if f and (ROOT / f).is_file()]
    for name in files:
        (dest / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, dest / name)
    return files


def _stand_in_base(base: str, tag: str, work: Path) -> str:
    """The debootstrapped base, made to stand in for python:3.11-slim; returns what differs, for the report.

    python:3.11-slim has no OpenMP runtime (the Dockerfile's runtime stage
    installs libgomp1 from Debian then), so it is removed here; and pip gets
    this machine's CA bundle, as a lab behind a TLS-inspecting proxy gives its
    base image its proxy's CA.
    """
    work.mkdir()
    lines = [f"FROM {base}", "LABEL nwr.build=1", "RUN dpkg --purge libgomp1 >/dev/null"]
    notes = ["libgomp1 removed"]
    bundle = next((Path(os.environ[v]) for v in CA_BUNDLES if os.environ.get(v)),
                  Path("/etc/ssl/certs/ca-certificates.crt"))
    if bundle.is_file():
        shutil.copy(bundle, work / "ca-certificates.crt")
        lines += ["COPY ca-certificates.crt /etc/ssl/certs/ca-certificates.crt",
                  "ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt"]
        notes.append(f"pip trusts this machine's CA bundle ({bundle})")
    (work / "Dockerfile").write_text("\n".join(lines) + "\n")
    _run(["docker", "build", "--quiet", "-t", tag, str(work)], timeout=300)
    return ", ".join(notes)


def test_online_build_from_a_clean_clone(compose: list[str], tmp_path: Path) -> None:
    """The documented online build, `docker build -f deploy/Dockerfile .` and compose's `build:`, from a clean clone.

    The same Dockerfile as the offline path, in its online form: no
    wheelhouse (the folder is in git, empty), PIP_NO_INDEX=0, every wheel
    from the package index through whatever the host offers (its network,
    its proxy variables, its CA bundle). What stands in: the debootstrapped
    base image of deploy/offline/build.sh (cached per machine) for
    python:3.11-slim, since no image registry is reachable here.
    """
    stages = Stages()
    pid = os.getpid()
    stand_in, image = f"nwr-online-base:test{pid}", f"nwr-online:test{pid}"
    try:
        _run(["bash", str(BUILD_SH), "base"], timeout=1800)
        base = _run(["bash", str(BUILD_SH), "base-tag"]).stdout.strip()
        notes = _stand_in_base(base, stand_in, tmp_path / "base")
        stages.done("base: stand-in for python:3.11-slim", f"{base}, {notes}")

        ctx = tmp_path / "clone"
        files = _clean_context(ctx)
        assert not list(ctx.rglob("*.whl")), "a clean clone has no wheels"
        stages.done("context: a clean clone", f"{len(files)} files")

        proxies = [a for v in PROXY_ARGS if os.environ.get(v) for a in ("--build-arg", f"{v}={os.environ[v]}")]
        build = _run(["docker", "build", "-f", "deploy/Dockerfile", "--build-arg", f"BASE={stand_in}", *proxies,
                      "-t", image, "."], timeout=1800, check=False, cwd=ctx)
        output = build.stdout + build.stderr
        assert build.returncode == 0, f"the online build failed from a clean clone:\n{output[-4000:]}"
        # pip took the wheels from the index (none came from a wheelhouse), and
        # the runtime stage installed OpenMP from Debian as on python:3.11-slim.
        downloaded = output.count("Downloading ")
        assert downloaded >= 20 and "Unpacking libgomp1" in output, output[-4000:]
        stages.done("docker build (online)", f"{downloaded} downloads from the package index")

        # The image works: the CLI, pinocchio (OpenMP), Zenoh; no pip; its user.
        assert "usage: nwr" in _run(["docker", "run", "--rm", image, "--help"], timeout=120).stdout
        probe = ("import importlib.util, os, pinocchio, zenoh, nwr.services.cli; "
                 "print(importlib.util.find_spec('pip') is None, os.getuid())")
        assert _run(["docker", "run", "--rm", "--entrypoint", "python", image, "-c", probe],
                    timeout=120).stdout.split() == ["True", "10001"]
        stages.done("image runs")

        # compose's build: (the same context and Dockerfile, so Docker's cache answers).
        env = {**os.environ, "NWR_IMAGE": image}
        _run([*compose, "-p", f"nwronline{pid}", "-f", str(ctx / "deploy" / "compose.yaml"), "build",
              "--build-arg", f"BASE={stand_in}", *proxies, "router"], timeout=1800, env=env)
        stages.done("compose build (cached)")
    finally:
        _run(["docker", "image", "rm", "--force", image, stand_in], check=False, timeout=120)
        # The builder stage's leftovers (label nwr.build=1), as build.sh prunes its own.
        _run(["docker", "image", "prune", "--force", "--filter", "label=nwr.build=1"], check=False, timeout=300)
        stages.done("images removed")
        print(stages.format().replace("compose test stages", "online build stages"))
