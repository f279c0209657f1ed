"""The ``fleethealth`` command reaches the tools, and a server installed without the client
package still starts while ``simulate`` and ``replay`` say what to install."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# Runs in a fresh interpreter where a finder refuses the client package, as if not installed.
_WITHOUT_CLIENT = textwrap.dedent(
    """
    import sys

    class Refuse:
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] == "fleethealth_client":
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, Refuse())
    from app.cli import main

    raise SystemExit(main(sys.argv[1:]))
    """
)


def _fleethealth_without_client(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _WITHOUT_CLIENT, *args],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.parametrize("tool", ["simulate", "replay"])
def test_tools_without_the_client_say_what_to_install(tool: str) -> None:
    done = _fleethealth_without_client(tool, "--url", "http://127.0.0.1:1", "--fast", "x.csv")
    assert done.returncode == 2, done.stderr
    assert f"fleethealth {tool}: the client package is not installed" in done.stderr
    assert "pip install ./clients/python" in done.stderr


def test_server_commands_build_without_the_client() -> None:
    done = _fleethealth_without_client("serve", "--help")
    assert done.returncode == 0, done.stderr
    assert "--demo" in done.stdout


def test_tools_are_sub_commands_with_their_options() -> None:
    from app.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["simulate", "--fast", "--transport", "ws", "--aircraft", "2"])
    assert (args.fast, args.transport, args.aircraft) == (True, "ws", 2)
    assert args.func.__module__ == "fleethealth_tools.simulate"
    args = parser.parse_args(["replay", "run.data.gz", "--tail", "N1", "--wait"])
    assert (args.paths, args.tail, args.wait) == (["run.data.gz"], "N1", True)
    assert args.func.__module__ == "fleethealth_tools.replay"
