"""Where a benchmark's figures came from: the command line and the commit, for its JSON file."""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def source_commit() -> str | None:
    """The checkout's short commit, with ``+`` appended when tracked files differ from it;
    ``None`` outside a git checkout."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=True
        ).stdout.strip()

    try:
        return git("rev-parse", "--short", "HEAD") + (
            "+" if git("status", "--porcelain", "-uno") else ""
        )
    except (OSError, subprocess.CalledProcessError):
        return None


def provenance(script: str, argv: list[str] | None) -> dict:
    """``{"command": ..., "commit": ...}`` for ``python benchmarks/<script>`` run with ``argv``
    (``sys.argv[1:]`` when ``None``)."""
    shown = sys.argv[1:] if argv is None else argv
    return {
        "command": shlex.join(["python", f"benchmarks/{script}", *shown]),
        "commit": source_commit(),
    }
