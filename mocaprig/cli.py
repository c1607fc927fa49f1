"""The ``mocaprig`` command line: a thin dispatcher over typed command functions.

Sub-command groups are discovered through the ``mocaprig.commands`` entry points (see
``pyproject.toml``). Each entry point is ``register(subparsers)``: it adds its parsers and sets
``func`` to a handler ``(argparse.Namespace) -> int``. Handlers import heavy modules lazily so
``mocaprig --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable, Sequence
from importlib.metadata import entry_points
from typing import Any, TextIO, get_args

from mocaprig import __version__
from mocaprig.errors import MocaprigError
from mocaprig.json_values import to_jsonable
from mocaprig.progress import ProgressMode, end_status_line, progress_mode

__all__ = [
    "Handler",
    "add_json_flag",
    "command_progress_mode",
    "emit_json",
    "main",
    "usage_handler",
]

_log = logging.getLogger(__name__)

Register = Callable[["argparse._SubParsersAction[argparse.ArgumentParser]"], None]
#: What every command's ``func`` is: a typed function of the parsed arguments -> exit code
#: (0 ok, 1 error, 2 usage, 3 data lost, 130 interrupted).
Handler = Callable[[argparse.Namespace], int]

_EPILOG = """\
examples:
  mocaprig demo --out demo-out                 simulate, record, calibrate, process; report
  mocaprig simulate --seconds 5 --out sim      simulated session: truth + Vicon C3D
  mocaprig vicon info capture.c3d --json       what a C3D or Nexus CSV holds
  mocaprig --progress always demo 2> demo.log  progress lines in a log file too

Run `mocaprig COMMAND --help` for a command's options and examples.
"""


def emit_json(obj: Any, *, stream: TextIO | None = None) -> None:
    """Print ``obj`` as one JSON object on one line of stdout."""
    out = sys.stdout if stream is None else stream
    out.write(json.dumps(to_jsonable(obj), sort_keys=False) + "\n")
    out.flush()


def usage_handler(parser: argparse.ArgumentParser) -> Handler:
    """The one usage handler: for a command group run without a sub-command, print the
    group's help on stderr and exit 2 (``parser.set_defaults(func=usage_handler(parser))``)."""

    def handler(_args: argparse.Namespace) -> int:
        parser.print_help(sys.stderr)
        return 2

    return handler


def add_json_flag(parser: argparse.ArgumentParser) -> None:
    """Add the standard ``--json`` flag (one JSON object on stdout)."""
    parser.add_argument(
        "--json", action="store_true", help="print one JSON object on stdout instead of text"
    )


def command_progress_mode(args: argparse.Namespace) -> ProgressMode:
    """The progress mode of a parsed command: ``never`` under ``-q`` or ``--json`` (stdout
    stays one JSON object and stderr quiet), else ``--progress`` (``auto`` by default)."""
    if getattr(args, "quiet", False) or getattr(args, "json", False):
        return "never"
    mode: ProgressMode = getattr(args, "progress", "auto")
    return mode


def _log_below_status_line(_record: logging.LogRecord) -> bool:
    """A log filter that lets every record through after ending a status line being drawn, so
    that the record starts on a line of its own."""
    end_status_line()
    return True


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mocaprig",
        description="Acquire, calibrate and process a DAVIS240C + RealSense D415 + Vicon rig.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mocaprig {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    parser.add_argument(
        "-q", "--quiet", action="store_true", help="only warnings and errors; no progress"
    )
    parser.add_argument(
        "--progress",
        choices=get_args(ProgressMode),
        default="auto",
        help="progress lines on stderr: on a terminal (auto, default), on any stream (always: "
        "a log file), or never; -q and --json imply never",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    eps = sorted(entry_points(group="mocaprig.commands"), key=lambda e: e.name)
    if not eps:
        _log.warning(
            "no mocaprig commands are registered; reinstall the package (pip install -e .)"
        )
    for ep in eps:
        try:
            register: Register = ep.load()
        except Exception:
            # One broken command group must not take the others down; say which and why.
            _log.exception("cannot load the '%s' commands (%s)", ep.name, ep.value)
            continue
        register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; return the process exit code (0 ok, 1 error, 2 usage)."""
    parser = _build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING if args.quiet else (logging.DEBUG if args.verbose else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    for handler in logging.getLogger().handlers:
        if _log_below_status_line not in handler.filters:
            handler.addFilter(_log_below_status_line)
    func: Handler = getattr(args, "func", None) or usage_handler(parser)
    try:
        with progress_mode(command_progress_mode(args)):
            return func(args)
    except MocaprigError as err:
        print(f"ERROR: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
