"""Writing result files atomically: a file is complete under its name, or absent.

Every JSON document is plain JSON: NumPy scalars and arrays become numbers and lists,
and a non-finite number is refused (a value that does not exist must be ``null``, with
its reason elsewhere in the document; see ``shared/CONTRACTS.md``).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path, PurePosixPath
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
#: Folders a run in progress fills and an interrupt removes whole (a study script's
#: staging folder, the cycles ``batch --cycles`` is splitting), and folders it made,
#: removed if they are left empty (see :func:`removed_if_interrupted`).
_PENDING_TREES: list[Path] = []
_PENDING_MADE: list[Path] = []


#: Set by :func:`remove_pending`: the process is ending, and a write that starts now
#: (in another thread) waits for the end instead.
_ENDING = threading.Event()


def remove_pending() -> None:
    """Remove the temporary files of every atomic write in progress, the folders a run
    in progress fills, and the folders it made if they are then empty: for a process
    that ends once it returns (signal handlers). Atomic writes that other threads start
    from now on wait, for ever."""
    _ENDING.set()
    for tmp in list(_PENDING):
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        _PENDING.discard(tmp)
    for tree in list(_PENDING_TREES):
        for _ in range(10):  # a thread may have written a file meanwhile
            shutil.rmtree(tree, ignore_errors=True)
            if not tree.exists():
                break
    for folder in reversed(list(_PENDING_MADE)):  # the innermost first
        with contextlib.suppress(OSError):
            folder.rmdir()  # only if empty


def missing_folders(folder: str | os.PathLike[str]) -> list[Path]:
    """The folders that making ``folder`` would create, outermost first."""
    missing = []
    probe = Path(folder)
    while not probe.exists() and probe != probe.parent:
        missing.append(probe)
        probe = probe.parent
    return missing[::-1]


@contextlib.contextmanager
def removed_if_interrupted(
    tree: str | os.PathLike[str] | None, made: Sequence[Path] = ()
) -> Iterator[None]:
    """While the block runs, an interrupt (:func:`remove_pending`) removes ``tree``
    whole (``None``: nothing) and each folder of ``made`` that is then empty; so does
    an exception out of the block. A block that ends normally keeps them."""
    trees = [] if tree is None else [Path(tree)]
    made = [Path(m) for m in made]
    _PENDING_TREES.extend(trees)
    _PENDING_MADE.extend(made)
    try:
        yield
    except BaseException:
        for t in trees:
            shutil.rmtree(t, ignore_errors=True)
        for folder in reversed(made):
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    finally:
        for t in trees:
            _PENDING_TREES.remove(t)
        for folder in made:
            _PENDING_MADE.remove(folder)


def _temp_beside(target: Path) -> Path:
    if _ENDING.is_set():  # the process is ending (remove_pending): write nothing more
        threading.Event().wait()
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


def _run_name(name: Any) -> bool:
    """Whether ``name`` from a run manifest is a file inside the folder: a relative
    path without ``..`` (a manifest is not trusted to name files elsewhere)."""
    if not isinstance(name, str) or not name or "\\" in name:
        return False
    path = PurePosixPath(name)
    return not path.is_absolute() and path.as_posix() == name and ".." not in path.parts


def earlier_run(folder: str | os.PathLike[str], run: str | None = None) -> list[str]:
    """The files an earlier run wrote into ``folder`` (from its :data:`RUN_MANIFEST`)
    that are still there, as paths relative to ``folder``; ``[]`` when there is none,
    or when ``run`` is given and the earlier run was not that one (see
    :func:`write_run`)."""
    folder = Path(folder)
    try:
        doc = json.loads((folder / RUN_MANIFEST).read_text(encoding="utf-8"))
        names = doc["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    if not isinstance(names, list) or (run is not None and doc.get("run") != run):
        return []
    return [n for n in names if _run_name(n) and (folder / n).is_file()]


def write_run(
    folder: str | os.PathLike[str],
    command: str,
    writers: Sequence[tuple[Path, Writer]],
    run: str | None = None,
):
    """Write one run's files into ``folder`` (created) as a set.

    The files (in ``folder`` or below it) are written atomically together
    (:func:`atomic_write`) with a :data:`RUN_MANIFEST` naming them (and ``run``, what
    was run, when given); then the files an earlier run wrote there and this one did
    not (e.g. an earlier diagnosis's ``finding_1_backlash.png`` beside a new verdict
    ``none``) are removed. Files the tool did not write are left alone.

    Returns
    -------
    list of Path
        The files written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    earlier = earlier_run(folder)
    targets = [Path(target) for target, _ in writers]
    names = [t.relative_to(folder).as_posix() for t in targets]
    for target in targets:
        target.parent.mkdir(parents=True, exist_ok=True)
    manifest = json_text({"command": command, "files": names} | ({"run": run} if run else {}))
    atomic_write(
        [(folder / RUN_MANIFEST, lambda tmp: tmp.write_text(manifest, encoding="utf-8"))]
        + [(t, w) for t, (_, w) in zip(targets, writers, strict=True)]
    )
    for name in earlier:
        if name not in names:
            (folder / name).unlink(missing_ok=True)
    return targets


#: The name of a run's staging folder inside its output folder (with the process id).
STAGING_PREFIX = ".ewb-ident-staging-"


@contextlib.contextmanager
def staged_run(folder: str | os.PathLike[str], run: str) -> Iterator[Path]:
    """A staging folder inside ``folder`` (created) for the files of a run that others
    write (a study script), holding copies of the files an earlier, complete run of
    the same ``run`` (see :func:`write_run`) left there, so that a script resumes from
    them (another run's files are replaced as a set, not mixed in).

    Move the staged files into place with :func:`write_run` and
    :func:`staged_writers` inside the block. The block's end removes the staging
    folder; an exception or an interrupt (:func:`remove_pending`) also removes
    ``folder`` and its parents if this run made them and they are empty. The earlier
    run's files stay as they were until :func:`write_run` replaces them as a set.
    """
    folder = Path(folder)
    stage = folder / f"{STAGING_PREFIX}{os.getpid()}"
    with removed_if_interrupted(stage, missing_folders(folder)):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            shutil.rmtree(stage, ignore_errors=True)  # a crashed run's of the same id
            stage.mkdir()
            for name in earlier_run(folder, run):
                (stage / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(folder / name, stage / name)
            yield stage
        finally:
            shutil.rmtree(stage, ignore_errors=True)


def staged_writers(
    stage: Path, folder: Path, skip: Sequence[str] = ()
) -> list[tuple[Path, Writer]]:
    """Writers (for :func:`write_run`) that move the files under ``stage`` to the same
    places under ``folder``, but for those named in ``skip`` (paths relative to the
    folder) and symbolic links."""
    writers: list[tuple[Path, Writer]] = []
    for path in sorted(stage.rglob("*")):
        name = path.relative_to(stage).as_posix()
        if path.is_symlink() or not path.is_file() or name in (*skip, RUN_MANIFEST):
            continue
        writers.append((folder / name, lambda tmp, src=path: os.replace(src, tmp)))
    return writers
