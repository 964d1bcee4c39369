"""The ``edgemodbus`` command: demo, run, read, write, plan, check, simulate, descriptor,
action, scan, templates, import.

Errors are one line per problem on stderr.  Exit codes, the same in every command: 0 ok,
1 a runtime failure (a device that never answered, a line that could not be opened, tag
rows refused), 2 a usage or configuration error, 130 interrupted (Ctrl-C).  Values print
so that they read back exactly: a float as its shortest round-trip form (``repr``;
``nan``, ``inf`` and ``-inf`` in text, ``null`` in JSON, which has no such numbers).
"""

# Start-up time (docs/benchmarks.md, "Start-up of the command line"): main() builds the
# options of the one command it runs and imports that command's module only; the others
# get a parser with their help line, so `edgemodbus read` loads neither the gateway, the
# simulator, scan's nor rich.

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from ..logs import LOG_FORMATS, configure_logging
from .exits import FAILED, INTERRUPTED, USAGE, CommandFailed
from .output import CliError, json_line, one_line, problem_lines, shortened, value_text

__all__ = ["build_parser", "json_line", "main", "value_text"]

_JSON_HELP = (
    "JSON lines on stdout instead of text: one object per item update "
    '{"device", "name", "value", "status", "updateTs", "errorReason"}, then, when polling '
    'stops, one {"device", "summary": {counters}} per device; nothing else goes to stdout. Floats '
    "are exact (shortest round-trip form); NaN and infinities are null"
)
_LOG_FORMAT_HELP = ("log lines as text (the default) or as JSON lines (time, level, logger, "
                    "message) for Loki/ELK; also after the command")


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (the usage is one ``-h`` away)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {shortened(one_line(message))} (see {self.prog} -h)\n")


def _version() -> str:
    """The installed distribution's version (pyproject.toml), else the package's."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("edgemodbus")
    except PackageNotFoundError:
        import edgemodbus

        return str(getattr(edgemodbus, "__version__", "unknown"))


class _VersionAction(argparse.Action):
    """``--version``: the distribution's version, looked up only when asked (reading the
    installed metadata costs ~10 ms of every start otherwise)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS,
                 **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        sys.stdout.write(f"edgemodbus {_version()}\n")
        parser.exit()


class _SubParser(_Parser):
    """A command's parser: also takes ``-v``/``-vv`` and ``--log-format`` after the
    command's name (it leaves the value given before it when absent)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                          help="log more (-vv: frame trace)")
        self.add_argument("--log-format", choices=LOG_FORMATS, default=argparse.SUPPRESS,
                          help=_LOG_FORMAT_HELP)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(_command_in(argv))
    args = parser.parse_args(argv)
    _logging(args)
    if args.command == "simulate":
        from ..sim.cli import run as simulate

        return simulate(args, parser)
    try:
        result: int = args.func(args)
        return result
    except (CliError, ValueError, OSError) as exc:
        for line in problem_lines(exc):
            print(f"edgemodbus {args.command}: {shortened(line)}", file=sys.stderr)
        return USAGE
    except CommandFailed as exc:
        for line in exc.lines:
            print(f"edgemodbus {args.command}: {shortened(line)}", file=sys.stderr)
        return FAILED
    except RecursionError:  # a backstop: config/ bounds the JSON depth it reads
        print(f"edgemodbus {args.command}: input nested too deeply to read", file=sys.stderr)
        return USAGE
    except KeyboardInterrupt:
        return INTERRUPTED


def _command_in(argv: Sequence[str]) -> str | None:
    """The command's name: the first word that is no option (the options before it,
    -v, --version, -h and --log-format, take no word of their own but --log-format)."""
    words = iter(argv)
    for word in words:
        if word == "--log-format":
            next(words, None)
        elif not word.startswith("-"):
            return word
    return None


def _logging(args: argparse.Namespace) -> None:
    """Warnings by default, the service (``run --config-dir``) info; each -v one step more
    (logs.py).  read and write report their outcome in their own line, so without -v
    they show the library's errors only: a refused connection is one line, not a warning
    and then the same error."""
    service = args.command == "run" and getattr(args, "config_dir", None) is not None
    configure_logging(args.verbose, default=logging.INFO if service else logging.WARNING,
                      quiet=getattr(args, "quiet", False), log_format=args.log_format)
    if not args.verbose and args.command in ("read", "write"):
        logging.getLogger("edgemodbus").setLevel(logging.ERROR)


def _call(module: str, name: str) -> Callable[[argparse.Namespace], int]:
    """The command function ``name`` of ``cli/module.py``, imported when it runs."""
    def command(args: argparse.Namespace) -> int:
        function: Callable[[argparse.Namespace], int] = getattr(
            importlib.import_module(f".{module}", __name__), name)
        return function(args)
    return command


def _module(name: str) -> Any:
    return importlib.import_module(f".{name}", __name__)


# -- the commands' options ---------------------------------------------------------------
def _demo(p: argparse.ArgumentParser) -> None:
    from ..sim.cli import slave_ids
    from .arg_types import seconds

    p.add_argument("--seconds", type=seconds, default=10.0, help="how long (10; 0 = until ^C)")
    p.add_argument("--slaves", type=slave_ids, default=[1, 2, 3],
                   help="slave ids on the line (1,2,3)")
    p.set_defaults(func=_call("polling", "demo"))


def _run(p: argparse.ArgumentParser) -> None:
    from ..gateway.run import add_arguments as add_service_arguments
    from .arg_types import path_text

    p.add_argument("files", nargs="*", type=path_text)
    add_service_arguments(p, config_dir_required=False)
    p.add_argument("--json", action="store_true", help=_JSON_HELP)
    p.set_defaults(func=_call("polling", "run"))


def _read_or_write(name: str) -> Callable[[argparse.ArgumentParser], None]:
    def add(p: argparse.ArgumentParser) -> None:
        from .line_options import add_line_options

        add_line_options(p)
        p.add_argument("address", help="e.g. hr:100, 3:00005, coil:5, hr:7.3")
        if name == "write":
            p.add_argument("value", help="value to write (number, true/false, text)")
        p.set_defaults(func=_call("oneshot" if name == "read" else "polling", name))
    return add


def _plan(p: argparse.ArgumentParser) -> None:
    from .arg_types import path_text

    p.add_argument("file", type=path_text)
    p.set_defaults(func=_call("polling", "plan"))


def _check(p: argparse.ArgumentParser) -> None:
    _module("check").add_arguments(p)
    p.set_defaults(func=_call("check", "run"))


def _simulate(p: argparse.ArgumentParser) -> None:
    from ..sim.cli import DESCRIPTION, add_arguments

    p.description = DESCRIPTION
    add_arguments(p)


def _descriptor(p: argparse.ArgumentParser) -> None:
    p.add_argument("--prefix", choices=["function-code", "modicon", "entity"],
                   default="function-code")
    p.set_defaults(func=_call("output", "print_descriptor"))


def _from_module(module: str) -> Callable[[argparse.ArgumentParser], None]:
    """Options and function of a command in its own module (``add_arguments``, ``run``)."""
    def add(p: argparse.ArgumentParser) -> None:
        _module(module).add_arguments(p)
        p.set_defaults(func=_call(module, "run"))
    return add


# name -> (help line, the module whose docstring is the description or None, add options)
_COMMANDS: dict[str, tuple[str, str | None, Callable[[argparse.ArgumentParser], None]]] = {
    "demo": ("poll a simulated line of slaves, print live values", None, _demo),
    "run": ("poll devices from device files, print updates; or run the gateway service with "
            "--config-dir", None, _run),
    "read": ("read one value", None, _read_or_write("read")),
    "write": ("write one value", None, _read_or_write("write")),
    "plan": ("show the read plan of a device file", None, _plan),
    "check": ("check device files, a gateway file or a config folder (nothing connects)",
              "check", _check),
    "simulate": ("serve simulated RTU slaves", None, _simulate),
    "action": ("run an action of a device file (NAME param=value ...), or list its actions",
               "action", _from_module("action")),
    "descriptor": ("print the driver descriptor JSON", None, _descriptor),
    "scan": ("find what answers on a line (settings, slave ids)", "scan",
             _from_module("scan")),
    "templates": ("list the device templates (or show one)", "templates",
                  _from_module("templates")),
    "import": ("turn a tag list (Kepware CSV export, or generic CSV) into a device file",
               "import_tags", _from_module("import_tags")),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole parser tree; with ``command`` only that command's options are built
    (and its module imported): the others are a name and a help line."""
    parser = _Parser(prog="edgemodbus", description=__doc__,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action=_VersionAction,
                        help="show the program's version number and exit")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more (-vv: frame trace); also after the command")
    parser.add_argument("--log-format", choices=LOG_FORMATS, default="text",
                        help=_LOG_FORMAT_HELP)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_SubParser)
    for name, (helptext, doc, add) in _COMMANDS.items():
        if command is not None and name != command:
            sub.add_parser(name, help=helptext)
            continue
        kwargs: dict[str, Any] = {}
        if doc is not None:
            kwargs = {"description": _module(doc).__doc__,
                      "formatter_class": argparse.RawDescriptionHelpFormatter}
        add(sub.add_parser(name, help=helptext, **kwargs))
    return parser
