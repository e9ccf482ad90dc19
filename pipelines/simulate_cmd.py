"""``tapost simulate SCENARIO -o DIR`` (not implemented yet)."""
from __future__ import annotations

import argparse

from logtools.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario")
    p.add_argument("-o", "--out", required=True)


def run(args: argparse.Namespace) -> int:
    raise InputError("simulate is not implemented yet")
