"""``tapost batch CAMPAIGN`` (not implemented yet)."""
from __future__ import annotations

import argparse

from logtools.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("campaign")
    p.add_argument("-o", "--out", default=None)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--scheduler", default=None)


def run(args: argparse.Namespace) -> int:
    raise InputError("batch is not implemented yet")
