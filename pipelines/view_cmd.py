"""``tapost view DIR|FILE.rrd``: open a recording in the rerun viewer (native, or ``--web`` in a browser)."""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys

from logtools.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("target", help="an analyze output directory or a .rrd file")
    p.add_argument("--web", action="store_true", help="serve the web viewer instead of the native one")


def run(args: argparse.Namespace) -> int:
    path = args.target
    if os.path.isdir(path):
        path = os.path.join(path, "recording.rrd")
    if not os.path.isfile(path):
        raise InputError("no recording found (expected a .rrd file or a folder holding recording.rrd)",
                         args.target)
    exe = shutil.which("rerun")
    cmd = [exe, path] if exe else [sys.executable, "-m", "rerun", path]
    if getattr(args, "web", False):
        cmd.append("--web-viewer")
    return subprocess.call(cmd)
