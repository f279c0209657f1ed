"""The ``simulate`` and ``replay`` sub-commands of the ``fleethealth`` command.

The tools need the client package (``fleethealth_client``), which is installed apart from the
server (``pip install ./clients/python``). A server installed without it still serves; the two
sub-commands are then listed and answer with what to install instead of failing at start-up.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

__all__ = ["CLIENT_MISSING", "TOOLS", "add_subcommands"]

#: Sub-command name -> one-line help.
TOOLS = {
    "simulate": "feed a running server with a simulated fleet",
    "replay": "send recorded files (e.g. FLEA runs) to a running server",
}
CLIENT_MISSING = (
    "fleethealth {tool}: the client package is not installed ({error}); "
    "install it with: pip install ./clients/python  (from the repository root)"
)
#: Exit code of a sub-command that cannot run in this installation.
EXIT_NOT_INSTALLED = 2


def add_subcommands(sub: Any) -> None:
    """Register ``simulate`` and ``replay`` on the sub-parsers of the ``fleethealth`` command.

    Args:
        sub: the object returned by ``ArgumentParser.add_subparsers``.
    """
    try:
        from fleethealth_tools import replay, simulate
    except ModuleNotFoundError as exc:
        if exc.name is None or exc.name.partition(".")[0] != "fleethealth_client":
            raise
        for tool, help_text in TOOLS.items():
            # No option prefix: every argument given is taken as-is, so the answer is the
            # message below rather than an argparse error about the options.
            sp = sub.add_parser(
                tool, help=f"{help_text} (needs the client package)", prefix_chars="\0"
            )
            sp.add_argument("args", nargs="*")
            sp.set_defaults(func=_not_installed(tool, exc))
        return
    sp = sub.add_parser("simulate", help=TOOLS["simulate"])
    simulate.add_arguments(sp)
    sp.set_defaults(func=simulate.run)
    sp = sub.add_parser("replay", help=TOOLS["replay"])
    replay.add_arguments(sp)
    sp.set_defaults(func=replay.run)


def _not_installed(tool: str, error: ModuleNotFoundError) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        del args  # whatever was given, the tool cannot run
        print(CLIENT_MISSING.format(tool=tool, error=error), file=sys.stderr)
        return EXIT_NOT_INSTALLED

    return run
