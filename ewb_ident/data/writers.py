"""Writing a trace: CSV with its JSON sidecar, atomically."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ewb_ident.data.outputs import atomic_write
from ewb_ident.data.trace import Trace, raise_trace_error

# --------------------------------------------------------------------------- writing


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def write_trace(
    trace: Trace,
    path: str | os.PathLike[str],
    *,
    extra: Sequence[tuple[Path, Callable[[Path], None]]] = (),
) -> Path:
    """Write a trace as CSV or Parquet, with its sidecar JSON beside it.

    Columns are ``time_s`` then the channels in :data:`COLUMNS` order, in SI units; CSV
    floats are written in their shortest exact form (``float(text)`` gives back the
    same float64). The sidecar (keys starting with ``_`` dropped) goes to
    ``NAME.json`` when it is not empty; an existing ``NAME.json`` beside an empty
    sidecar is replaced by ``{}`` so that it cannot lend stale facts to the new table.
    Each file is written to a temporary file in the same folder and moved into place
    with :func:`os.replace`, so no half-written file is ever left under the target name.

    Parameters
    ----------
    trace
        The trace to write.
    path
        ``NAME.csv`` or ``NAME.parquet``.
    extra
        More files written in the same set (``simulate``'s truth): every file is
        written, or none.

    Returns
    -------
    Path
        The path of the table written.

    Raises
    ------
    TraceError
        For another suffix, a sidecar value that JSON cannot hold, or a folder that
        cannot be written.
    """
    path = Path(path)
    label = str(path)
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet"):
        raise_trace_error(label, f"cannot write {path.suffix!r} files", "write .csv or .parquet")
    side_path = path.with_suffix(".json")
    public = {k: v for k, v in trace.sidecar.items() if not str(k).startswith("_")}
    side_text: str | None = None
    if public or side_path.exists():
        try:
            side_text = json.dumps(public, indent=2, default=_json_default) + "\n"
        except (TypeError, ValueError) as err:
            raise_trace_error(
                str(side_path), f"sidecar cannot be written as JSON ({err})", "fix the value"
            )

    frame = trace.to_frame()
    writers: list[tuple[Path, Callable[[Path], None]]] = []
    if suffix == ".csv":
        writers.append(
            (path, lambda tmp: frame.to_csv(tmp, index=False, na_rep="", lineterminator="\n"))
        )
    else:

        def _parquet(tmp: Path) -> None:
            import pyarrow as pa
            import pyarrow.parquet as pq

            pq.write_table(pa.table({c: pa.array(frame[c].to_numpy()) for c in frame}), tmp)

        writers.append((path, _parquet))
    if side_text is not None:
        text = side_text
        writers.append((side_path, lambda tmp: tmp.write_text(text, encoding="utf-8")))
    writers += list(extra)

    try:
        atomic_write(writers)
    except OSError as err:
        raise_trace_error(
            label,
            f"cannot write ({err.strerror or err})",
            "check the folder exists and is writable",
        )
    return path
