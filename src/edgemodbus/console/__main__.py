"""``python -m edgemodbus.console hash-password``: the ``passwordHash`` of a console
user (console/auth.py), read from the terminal (or one line of standard input)."""

from __future__ import annotations

import argparse
import getpass
import sys
from collections.abc import Sequence

from .auth import hash_password


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m edgemodbus.console",
                                     description="Tools of the gateway's web console.")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("hash-password", help="print the passwordHash of a password (scrypt) "
                   "for the gateway file's console.users")
    parser.parse_args(argv)
    if sys.stdin.isatty():
        password = getpass.getpass("password: ")
        if getpass.getpass("again: ") != password:
            print("the two passwords differ", file=sys.stderr)
            return 2
    else:
        password = sys.stdin.readline().rstrip("\r\n")
    try:
        print(hash_password(password))
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
