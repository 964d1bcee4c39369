"""The exit codes of every ``edgemodbus`` command (docs/command-line.md, "Exit codes").

``python -m edgemodbus.gateway`` and ``python -m edgemodbus.sim`` use the same numbers
(their layers sit below this one and spell them out)."""

OK = 0
"""The command did what it was asked."""
FAILED = 1
"""A runtime failure: a device that never answered, a line that could not be opened,
tag rows that were refused."""
USAGE = 2
"""A usage or configuration error: a bad option or file, a missing optional package, a
port in use; one line per problem naming the option or field."""
INTERRUPTED = 130
"""Stopped by SIGINT (Ctrl-C); SIGTERM is a normal stop (0)."""


class CommandFailed(Exception):
    """A runtime failure (exit code FAILED): one line per problem on stderr."""

    def __init__(self, *lines: str) -> None:
        super().__init__("\n".join(lines))
        self.lines = [" ".join(line.split()) for line in lines]
