"""Argument types shared by the benchmark scripts: counts are checked when the command line
is parsed, so a bad one is named before anything is built or timed."""

from __future__ import annotations

import argparse
from collections.abc import Callable


def count(least: int = 1) -> Callable[[str], int]:
    """An argparse ``type`` for an integer of at least ``least``: ``--steps 0`` stops with
    "argument --steps: must be an integer >= 1, got '0'"."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < least:
            raise argparse.ArgumentTypeError(f"must be an integer >= {least}, got {text!r}")
        return value

    parse.__name__ = f"integer >= {least}"
    return parse
