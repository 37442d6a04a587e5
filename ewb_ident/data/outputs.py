"""Writing result files atomically: a file is complete under its name, or absent.

Every JSON document is plain JSON: NumPy scalars and arrays become numbers and lists,
and a non-finite number is refused (a value that does not exist must be ``null``, with
its reason elsewhere in the document; see ``shared/CONTRACTS.md``).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

Writer = Callable[[Path], None]


def plain(value: Any) -> Any:
    """``value`` with NumPy types turned into plain Python ones, recursively."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def null_nonfinite(value: Any) -> Any:
    """``value`` (plain types) with every NaN or infinity replaced by ``None``: for
    documents of a diverged computation, whose reason the document states elsewhere."""
    value = plain(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: null_nonfinite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [null_nonfinite(v) for v in value]
    return value


def json_text(document: Any) -> str:
    """Pretty JSON text of ``document``.

    Raises
    ------
    ValueError
        If it holds NaN or infinity (name the key path).
    """
    doc = plain(document)
    bad = _nonfinite(doc, "")
    if bad:
        raise ValueError(f"non-finite number at {bad}: write null and say why instead")
    return json.dumps(doc, indent=2, allow_nan=False) + "\n"


def _nonfinite(value: Any, where: str) -> str | None:
    if isinstance(value, float) and not math.isfinite(value):
        return where or "<root>"
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, list):
        items = enumerate(value)
    else:
        return None
    for k, v in items:
        found = _nonfinite(v, f"{where}.{k}" if where else str(k))
        if found:
            return found
    return None


#: Temporary files of atomic writes in progress, so that an interrupt (SIGINT, SIGTERM)
#: can remove them before the process ends (see :func:`remove_pending`).
_PENDING: set[Path] = set()


def remove_pending() -> None:
    """Remove the temporary files of every atomic write in progress (signal handlers)."""
    for tmp in list(_PENDING):
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        _PENDING.discard(tmp)


def _temp_beside(target: Path) -> Path:
    fd, name = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    _PENDING.add(Path(name))
    os.close(fd)
    os.chmod(name, target.stat().st_mode & 0o777 if target.exists() else 0o644)
    return Path(name)


def atomic_write(writers: Sequence[tuple[Path, Writer]]) -> None:
    """Write several files so that each is either complete under its name or untouched.

    Each writer fills a temporary file in its target's folder; only when every writer
    has succeeded are the temporary files moved into place (:func:`os.replace`), in
    reverse order (so a table's sidecar lands before the table). On any error the
    temporary files are removed and the targets are left as they were.

    Raises
    ------
    OSError
        From a writer or the file system (the caller turns it into a message).
    """
    temps: list[tuple[Path, Path]] = []
    try:
        for target, write in writers:
            tmp = _temp_beside(target)
            temps.append((tmp, target))
            write(tmp)
            with open(tmp, "rb") as handle:
                os.fsync(handle.fileno())
        for tmp, target in reversed(temps):
            os.replace(tmp, target)
    finally:
        for tmp, _ in temps:
            tmp.unlink(missing_ok=True)
            _PENDING.discard(tmp)


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_write`)."""
    path = Path(path)
    atomic_write([(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))])
    return path


def write_json(path: str | os.PathLike[str], document: Any) -> Path:
    """Write ``document`` as JSON to ``path`` atomically (see :func:`json_text`)."""
    return write_text(path, json_text(document))
