"""Learned classifier model files (``.npz``, docs/models.md): read, validated, written.

The arrays and their checks are :meth:`estimator.models.learned.LearnedClassifier.from_arrays`'s;
this module adds what a file needs: a size limit checked before anything is read, no pickled
objects (``allow_pickle=False``), and a SHA-256 digest so a scenario can tell the file it was
validated against from one replaced since.
"""

from __future__ import annotations

import functools
import hashlib
import io
import zipfile
from pathlib import Path

import numpy as np

from estimator.models.learned import LearnedClassifier, LearnedModelError

__all__ = ["MAX_FILE_BYTES", "LearnedFileError", "load_learned", "save_learned"]

MAX_FILE_BYTES = 64 * 2**20


class LearnedFileError(ValueError):
    """A learned model file cannot be used; the message names the file and the field."""


def load_learned(path: str | Path, digest: str | None = None) -> tuple[LearnedClassifier, str]:
    """The model in ``path`` and the SHA-256 of its bytes; with ``digest``, the bytes must have
    that digest (the file was not replaced since it was validated)."""
    path = Path(path)
    data = _read(path)
    found = hashlib.sha256(data).hexdigest()
    if digest is not None and found != digest:
        raise LearnedFileError(f"{path}: the file changed since the scenario was loaded")
    return _parse(data, str(path)), found


@functools.lru_cache(maxsize=16)
def _parse(data: bytes, label: str) -> LearnedClassifier:
    # Cached on the bytes: every belief a study builds shares one model object.
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:  # a small file may inflate to a huge one
            inflated = sum(info.file_size for info in archive.infolist())
        if inflated > MAX_FILE_BYTES:
            raise LearnedFileError(f"{label}: inflates to {inflated} bytes, more than allowed")
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise LearnedFileError(f"{label}: not a readable .npz file: {reason}") from None
    try:
        return LearnedClassifier.from_arrays(arrays)
    except LearnedModelError as exc:
        raise LearnedFileError(f"{label}: {exc}") from None


def _read(path: Path) -> bytes:
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise LearnedFileError(f"{path}: {size} bytes, more than {MAX_FILE_BYTES} allowed")
        return path.read_bytes()
    except FileNotFoundError:
        raise LearnedFileError(f"{path}: no such learned model file") from None
    except OSError as exc:
        raise LearnedFileError(f"{path}: cannot read: {exc.strerror or exc}") from None


def save_learned(model: LearnedClassifier, path: str | Path) -> Path:
    """Write ``model`` to ``path`` (``.npz``, uncompressed); returns the path written."""
    path = Path(path)
    buffer = io.BytesIO()
    np.savez(buffer, allow_pickle=False, **model.to_arrays())
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buffer.getvalue())
    return path
