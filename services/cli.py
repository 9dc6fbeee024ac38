"""The ``nwr`` command: the parser and the dispatch, nothing else.

``nwr run SERVICE`` runs one service (its ``main.py``), and imports only
that service's code; every other command is registered by its tool module
(``register(subparsers)``, whose parsers ``set_defaults(handler=fn(args) ->
int)``).
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import re
import sys
from importlib import import_module
from typing import Any

from nwr.common.errors import NwrError
from nwr.common.launch import env_overrides, insecure
from nwr.common.node import setup_logging
from nwr.services.pipeline.graph import SERVICES, process_name

log = logging.getLogger("nwr")

# Modules that add subcommands of their own (see build_parser).
COMMAND_MODULES: list[str] = [
    "nwr.services.tools.demo",
    "nwr.services.tools.recordings.summary",
    "nwr.services.tools.press",
    "nwr.services.recorder.commands",
    "nwr.services.tools.figures",
    "nwr.services.view.commands",
    "nwr.services.tools.switch",
    "nwr.services.tools.safety",
    "nwr.services.tools.status",
    "nwr.services.tools.router",
    "nwr.services.tools.recordings.replay",
    "nwr.services.tools.recordings.compare",
    "nwr.services.tools.recordings.rosbag_import",
    "nwr.services.tools.recordings.export",
    "nwr.services.tools.recordings.verify",
    "nwr.services.tools.study.main",
    "nwr.services.tools.bench.main",
    "nwr.services.tools.certs",
]


def _service_module(name: str) -> Any:
    return import_module(f"nwr.services.{name}.main")


def build_parser(service: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; with ``service``, only ``nwr run SERVICE`` (a service's process loads its own code)."""
    parser = argparse.ArgumentParser(
        prog="nwr",
        description="Tactile withdrawal reflexes for a skin-covered robot arm: Zenoh services, launcher and tools.",
    )
    parser.add_argument("--profile", "-p", default=os.environ.get("NWR_PROFILE", "default"),
                        help="profile: a packaged name or a .toml path (default: $NWR_PROFILE or 'default')")
    parser.add_argument("--log-level", default=os.environ.get("NWR_LOG_LEVEL", "INFO"),
                        help="logging level (default: INFO)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run one service in the foreground",
                         description="Run one service as its own process until Ctrl-C or SIGTERM.")
    run_sub = run.add_subparsers(dest="service", required=True, metavar="SERVICE")
    for name, doc in SERVICES.items():
        if service is not None and name != service:
            continue
        p = run_sub.add_parser(name, help=doc, description=doc)
        _service_module(name).add_arguments(p)
        p.set_defaults(handler=_run_service)

    for name in COMMAND_MODULES if service is None else ():
        import_module(name).register(sub)
    _plain_help(parser)
    return parser


def _run_service(args: argparse.Namespace) -> Any:
    from nwr.services.profile import PACKAGES, profile_for

    # A service checks its own plug-ins' tables (a launch checked them all); the recorder keeps every loosened
    # value, the plug-ins' included, in the session's metadata.
    sections = PACKAGES if args.service == "recorder" else [s for s in PACKAGES if s == args.service]
    return _service_module(args.service).run(profile_for(args, sections), args)


# Many descriptions are their module's docstring, written for Sphinx: ``literal``, :role:`target` (:func:`~a.b`
# shows as b), which `--help` would print as they are.
_LITERAL = re.compile(r"``(.+?)``", re.S)
_ROLE = re.compile(r":(?:mod|func|class|meth|attr|data|exc|obj):`(~?)([^`]+)`")


def plain_text(text: str) -> str:
    """reStructuredText's inline markup taken out of ``text``: ``x`` -> x, :func:`~a.b` -> b, :mod:`a.b` -> a.b."""
    text = _ROLE.sub(lambda mt: mt[2].rsplit(".", 1)[-1] if mt[1] else mt[2], text)
    return _LITERAL.sub(r"\1", text)


def _plain_help(parser: argparse.ArgumentParser) -> None:
    """Every description, epilog and option help of ``parser`` and its subcommands in plain text."""
    parser.description = parser.description and plain_text(parser.description)
    parser.epilog = parser.epilog and plain_text(parser.epilog)
    for action in parser._actions:
        if isinstance(action.help, str):
            action.help = plain_text(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                choice.help = choice.help and plain_text(choice.help)
            for sub in set(action.choices.values()):
                _plain_help(sub)


def _service_run(argv: list[str]) -> str | None:
    """The service of ``nwr [options] run SERVICE ...``, else None (every other command builds the whole parser)."""
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--profile", "-p")
    pre.add_argument("--log-level")
    _, rest = pre.parse_known_args(argv)
    return rest[1] if len(rest) > 1 and rest[0] == "run" and rest[1] in SERVICES else None


def log_label(args: argparse.Namespace) -> str:
    """What every log line of this process is labelled with: the command, or the service it runs (a planner
    named on the command line by its process name, ``planner-<name>``, so that several planners' lines differ)."""
    if args.command != "run":
        return str(args.command)
    return process_name(args.service, getattr(args, "name", None) or getattr(args, "reflex", None))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(_service_run(argv))
    args = parser.parse_args(argv)
    setup_logging(args.log_level, log_label(args))
    try:
        # Read here, not at import: flags and environment override the profile in main.
        args.env_overrides = env_overrides(os.environ)
        if insecure(args.env_overrides):
            log.warning("NWR_INSECURE=1: secure mode is OFF (no TLS, no access control): anyone who reaches the "
                        "router can move the arm; for a first try on a trusted network only")
        return int(args.handler(args) or 0)
    except (NwrError, FileNotFoundError) as exc:
        log.error("%s", exc)
        return 2
    finally:
        # Free the trajectory generators (nanobind objects caught in reference
        # cycles) before the interpreter tears their module down, which would
        # otherwise report them as leaked on exit.
        gc.collect()


if __name__ == "__main__":
    sys.exit(main())
