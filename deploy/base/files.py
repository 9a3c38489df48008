"""Files written whole: a reader, or a command stopped half-way, never finds half a file."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path


def write_atomically(path: Path, write: Callable[[Path], object]) -> Path:
    """Call ``write`` with a temporary path next to ``path``, then rename it to ``path``.

    The temporary file is in the same folder, so that the rename (``os.replace``) is atomic, and
    ends in the same suffix, for writers that choose the format by it (matplotlib). If ``write``
    fails, or the command is stopped, the temporary file is removed and ``path`` is untouched.
    Returns ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_text_atomically(path: Path, text: str) -> Path:
    """:func:`write_atomically` for UTF-8 text."""
    return write_atomically(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
