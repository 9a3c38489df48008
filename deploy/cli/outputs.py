"""Where a command writes: one rule for every command that writes files, checked before the
command does its work (README.md, "Where commands write").

- An output file (``-o FILE``, ``--plot``, ``--record``) that exists, or an output folder
  (``--out DIR``) that is not empty, is refused unless ``--force``; with it, the command writes
  its files over the old ones and leaves every other file of the folder alone. (`fleet init`
  is stricter: a fleet's keys are never written over, so it has no ``--force``.)
- The folder of an output must be one the command can create and write in.
- A figure's suffix names its format (:data:`FIGURE_SUFFIXES`); a figure named without one gets
  ``.png``, a figure named by a folder goes into it as ``<default name>.png``.

Each is a :class:`UsageError` naming the option (exit 2) before any work: a long run does not
find out at its end, and a refused output leaves nothing behind. Files are then written whole
(:mod:`deploy.base.files`).
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

from deploy.base.errors import UsageError

FIGURE_SUFFIXES = (".png", ".pdf", ".svg")
FORCE_HELP = "write over an existing output (without it, an existing one is refused)"


def add_force(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true", help=FORCE_HELP)


def new_file(path: Path, option: str, force: bool) -> Path:
    """Check that ``path``, the file ``option`` names, may be written; returns it."""
    if path.is_dir():
        raise UsageError(f"{option} {path}: is a folder, not a file")
    if (path.exists() or path.is_symlink()) and not force:
        raise UsageError(f"{option} {path}: already exists (--force overwrites it)")
    _can_create_in(path.parent, option, path)
    return path


def new_folder(path: Path, option: str, force: bool) -> Path:
    """Check that ``path``, the folder ``option`` names, is new or empty (or ``force``) and can
    be made and written in; returns it (created by whoever writes in it)."""
    if path.exists() and not path.is_dir():
        raise UsageError(f"{option} {path}: is a file, not a folder")
    if path.is_dir() and not force and any(path.iterdir()):
        raise UsageError(
            f"{option} {path}: exists and is not empty (--force writes over the outputs in it)"
        )
    _can_create_in(path, option, path)
    return path


def figure_file(text: str, option: str, force: bool, default_name: str) -> tuple[Path, str]:
    """The figure file that ``option TEXT`` names, checked as :func:`new_file`, and a note for the
    "wrote" line when that file is not TEXT as typed ("" when it is).

    A folder (an existing one, or TEXT ending in a slash) gets ``default_name``.png in it; a
    name without a suffix gets ``.png``; any other suffix than :data:`FIGURE_SUFFIXES` is an
    error (matplotlib would pick the format by it, or fail on it)."""
    path = Path(text)
    note = ""
    if text.endswith(("/", os.sep)) or path.is_dir():
        path = path / f"{_file_name(default_name)}.png"
        note = f"{option} {text} is a folder"
    elif not path.suffix:
        path = path.with_name(f"{path.name}.png")
        note = f"{option} {text} has no suffix: .png added"
    elif path.suffix.lower() not in FIGURE_SUFFIXES:
        formats = ", ".join(FIGURE_SUFFIXES)
        raise UsageError(f"{option} {text}: {path.suffix} is not a figure format ({formats})")
    return new_file(path, option, force), note


def _file_name(name: str) -> str:
    """``name`` as one file name: a scenario's name may hold a colon or a slash."""
    return re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip(".-") or "figure"


def _can_create_in(folder: Path, option: str, named: Path) -> None:
    """Check, without creating anything, that ``folder`` is or can be made a folder we write in:
    its nearest existing ancestor is a folder we may write in."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise UsageError(f"{option} {named}: cannot write there ({existing} is a file)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {named}: cannot write there ({existing}: permission denied)")
