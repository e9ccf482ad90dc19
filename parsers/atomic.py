"""Atomic file output: write to a temporary sibling, then rename over the target."""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator

from logtools.errors import InputError


@contextlib.contextmanager
def atomic_path(path: str) -> Iterator[str]:
    """Yield a temporary path next to ``path``; on success it replaces ``path``, else is removed."""
    d = os.path.dirname(os.path.abspath(path)) or "."
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp", dir=d)
    os.close(fd)
    try:
        yield tmp
        if os.path.isfile(tmp):  # mkstemp makes 0600: give the file the mode open() would (umask)
            mask = os.umask(0)
            os.umask(mask)
            os.chmod(tmp, 0o666 & ~mask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def replace_path(tmp: str, dst: str, aside: str) -> None:
    """Move a finished ``tmp`` (a file or a folder, e.g. a ROS 2 bag) onto ``dst``: an existing ``dst`` is
    renamed to ``aside`` first and removed once ``tmp`` is in place (a folder cannot be replaced in one
    rename)."""
    old = None
    if os.path.exists(dst):
        old = aside
        os.rename(dst, old)
    os.rename(tmp, dst)
    if old:
        shutil.rmtree(old, ignore_errors=True) if os.path.isdir(old) else os.remove(old)


def check_replaceable(path: str, same_kind: Callable[[str], bool], what: str) -> None:
    """InputError unless a folder output ``what`` may go to ``path``: nothing there, an empty folder, or a folder
    ``same_kind`` says is an earlier output of its kind. A file, or a folder of other things, is never replaced
    by one (`-o` naming a file or an output folder once put a ROS 2 bag in their place)."""
    if not os.path.lexists(path):
        return
    if os.path.islink(path) or not os.path.isdir(path):
        raise InputError(f"exists and is not a folder: a {what} is one (not replaced; give another output path)",
                         path)
    if os.listdir(path) and not same_kind(path):
        raise InputError(f"exists and holds other files than a {what} (not replaced; give another output path, "
                         "or remove it)", path)


@contextlib.contextmanager
def atomic_folder(path: str, name: str = "bag", same_kind: Callable[[str], bool] | None = None,
                  what: str = "folder") -> Iterator[str]:
    """Yield a not yet existing path ``name`` inside a temporary folder next to ``path`` (a folder output,
    e.g. a ROS 2 bag, is written there); on success it replaces ``path`` (:func:`replace_path`); the
    temporary folder is removed in any case."""
    if same_kind is not None:
        check_replaceable(path, same_kind, what)
    parent = os.path.dirname(os.path.abspath(path)) or "."
    os.makedirs(parent, exist_ok=True)
    tmpdir = tempfile.mkdtemp(prefix="." + os.path.basename(path) + ".", dir=parent)
    try:
        tmp = os.path.join(tmpdir, name)
        yield tmp
        replace_path(tmp, path, tmpdir + ".old")
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
