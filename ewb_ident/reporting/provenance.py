"""The report's provenance: what made it (tool, commit, package versions, command,
seeds) and from what (each trace's file, hash, rate, pad radius and column mapping)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from html import escape as esc
from pathlib import Path
from typing import TYPE_CHECKING

from ewb_ident.data.campaign import file_hash

if TYPE_CHECKING:
    from ewb_ident.data.trace import Trace

#: Packages whose versions the report's provenance lists (they make its numbers).
PROVENANCE_PACKAGES = ("jax", "numpy", "scipy", "equinox", "optimistix", "emcee", "arviz")


def package_versions(names: Sequence[str]) -> dict[str, str | None]:
    """The installed version of each distribution in ``names`` (``None``: not installed)."""
    from importlib import metadata

    out: dict[str, str | None] = {}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def _checkout_commit() -> str:
    """The commit of the checkout the package runs from, or ``""`` (an installed copy)."""
    import subprocess

    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return ""
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5
        )
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""


def provenance_rows(
    traces: Sequence[Trace], command: str | None, seeds: Sequence[int]
) -> list[list[str]]:
    """The report's provenance as (item, HTML value) rows: tool version (and commit, from
    a checkout), the versions of the packages its numbers come from, date, command, seeds
    and, per trace, file, SHA-256, r_eff and its source, and the column mapping with its
    unit conversions."""
    import datetime

    commit = _checkout_commit()
    found = package_versions(("ewb-ident", *PROVENANCE_PACKAGES))
    shown = {p: v or "not installed" for p, v in found.items()}
    rows = [
        ["tool", esc(f"ewb-ident {shown.pop('ewb-ident')}")],
        *([["commit", f"<code>{esc(commit)}</code>"]] if commit else []),
        ["packages", esc(", ".join(f"{p} {v}" for p, v in shown.items()))],
        ["date (UTC)", esc(datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M"))],
    ]
    if command:
        rows.append(["command", f"<code>{esc(command)}</code>"])
    if seeds:
        rows.append(["MCMC seeds", esc(", ".join(str(int(x)) for x in seeds))])
    for t in traces:
        digest = "–"
        if t.path is not None and Path(t.path).is_file():
            digest = file_hash(t.path)
        mapped = ", ".join(
            f"{m.get('source', col)}"
            + (f" [{m['unit']} → SI]" if m.get("unit") else "")
            + f" → {col}"
            for col, m in t.sidecar.get("_mapped", {}).items()
            if isinstance(m, Mapping)
        )
        rows += [
            [f"trace {esc(t.name)}", esc(t.label)],
            ["  SHA-256", f"<code>{digest}</code>"],
            ["  samples", esc(f"{t.n} at {t.sample_rate_hz:g} Hz, {t.duration_s:g} s")],
            ["  r_eff", esc(f"{t.r_eff_m:g} m ({t.r_eff_source})")],
            ["  column mapping", esc(mapped or "none (the file's own column names)")],
        ]
    return rows
