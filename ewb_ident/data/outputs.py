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


def json_writer(document: Any) -> Writer:
    """A writer of ``document`` as JSON (see :func:`json_text`; checked now, not when
    it writes)."""
    text = json_text(document)
    return lambda tmp: tmp.write_text(text, encoding="utf-8")


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_write`)."""
    path = Path(path)
    atomic_write([(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))])
    return path


def write_json(path: str | os.PathLike[str], document: Any) -> Path:
    """Write ``document`` as JSON to ``path`` atomically (see :func:`json_text`)."""
    return write_text(path, json_text(document))


#: The list of files a command wrote into its output folder (``--out``), beside them, so
#: that the next run into that folder replaces them as a set.
RUN_MANIFEST = ".ewb-ident-run.json"


def earlier_run(folder: str | os.PathLike[str]) -> list[str]:
    """The files an earlier run wrote into ``folder`` (from its :data:`RUN_MANIFEST`)
    that are still there; ``[]`` when there is none."""
    folder = Path(folder)
    try:
        doc = json.loads((folder / RUN_MANIFEST).read_text(encoding="utf-8"))
        names = doc["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    if not isinstance(names, list):
        return []
    safe = [n for n in names if isinstance(n, str) and n and Path(n).name == n]
    return [n for n in safe if (folder / n).is_file()]


def write_run(folder: str | os.PathLike[str], command: str, writers: Sequence[tuple[Path, Writer]]):
    """Write one run's files into ``folder`` (created) as a set.

    The files are written atomically together (:func:`atomic_write`) with a
    :data:`RUN_MANIFEST` naming them; then the files an earlier run wrote there and
    this one did not (e.g. an earlier diagnosis's ``finding_1_backlash.png`` beside a
    new verdict ``none``) are removed. Files the tool did not write are left alone.

    Returns
    -------
    list of Path
        The files written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    earlier = earlier_run(folder)
    names = [Path(target).name for target, _ in writers]
    manifest = json_text({"command": command, "files": names})
    atomic_write(
        [(folder / RUN_MANIFEST, lambda tmp: tmp.write_text(manifest, encoding="utf-8"))]
        + [(Path(t), w) for t, w in writers]
    )
    for name in earlier:
        if name not in names:
            (folder / name).unlink(missing_ok=True)
    return [Path(target) for target, _ in writers]
