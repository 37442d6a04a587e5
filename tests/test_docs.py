"""The documentation: the site builds in strict mode, and its examples are true.

Rules enforced here:

* ``mkdocs build --strict`` passes: no broken link or anchor, no page outside the nav
  unless a page links to it, no docstring the API reference cannot read; the command-line
  reference holds every command.
* Every ```python block of the pages runs as written, in order, page by page, from the
  repository's root.
* Every ```bash block of the pages runs as written (``ewb-ident`` being this
  interpreter's) in an empty folder beside the shipped ``datasets/``; the ones that take
  minutes are marked slow.
* Every command synopsis (a plain ``` block of ``ewb-ident COMMAND [--option ...]``) names
  only options the command has.
* A ```toml block that shows a shipped file holds what that file holds, and the tool
  reads it.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(DOCS.glob("*.md"))
#: The README is a page of the site too ("Quick tour").
PAGES_AND_README = [*PAGES, ROOT / "README.md"]
#: ```bash examples that take minutes (the main job and the README's whole tour).
SLOW_SHELL = {"report.md": "the main job", "README.md": "the whole quick tour"}
BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", flags=re.S | re.M)


def _blocks(path: Path, language: str) -> list[str]:
    return [code for lang, code in BLOCK.findall(path.read_text(encoding="utf-8"))
            if lang == language]  # fmt: skip


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


# --- the site ----------------------------------------------------------------------------


def test_the_site_builds_in_strict_mode(tmp_path):
    """`mkdocs build --strict` fails on any warning: a broken link or anchor, a page
    left out of the nav, a docstring the API reference cannot parse. The generated
    pages hold what they are generated from."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "PYTHONPATH": str(ROOT)}
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "WARNING" not in proc.stderr, proc.stderr[-4000:]
    cli = (site / "cli" / "index.html").read_text(encoding="utf-8")
    from ewb_ident.cli import app

    for info in app.registered_commands:
        name = info.name or info.callback.__name__
        assert f"ewb-ident {name} --help" in cli, name
    api = (site / "api" / "index.html").read_text(encoding="utf-8")
    for name in ("ewb_ident.fit", "ewb_ident.sample", "ewb_ident.diagnose", "read_trace"):
        assert name in api, name
    bench = (site / "benchmarks" / "index.html").read_text(encoding="utf-8")
    for path in (ROOT / "reports").glob("bench_*.md"):
        assert f"reports/{path.name}" in bench, path.name
    # a page's link to a file outside docs/ reaches a page of the site
    assert (site / "repo" / "CHANGELOG" / "index.html").exists()


# --- code examples ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "page", [p for p in PAGES_AND_README if _blocks(p, "python")], ids=lambda p: p.name
)
def test_the_python_examples_run(page, tmp_path):
    """Every ```python block of a page runs as written, in order, in a folder that shows
    the repository's files (the datasets it names are shipped) and takes what the
    examples write (nothing is left in the repository)."""
    blocks = _blocks(page, "python")
    for item in ROOT.iterdir():
        if not item.name.startswith("."):
            (tmp_path / item.name).symlink_to(item)
    here = os.getcwd()
    os.chdir(tmp_path)
    try:
        scope: dict = {}
        for k, code in enumerate(blocks):
            exec(compile(code, f"{_rel(page)} python block {k + 1}", "exec"), scope)
    finally:
        os.chdir(here)


#: Lines of a README block that set up what this test already runs in: installing the
#: package, and the test suite itself.
SET_UP = re.compile(
    r"^python -m pip install -e \S+(?: && python -m pytest\b.*$| && )?|^python -m pytest\b.*$", re.M
)


def _shell_pages():
    for page in PAGES_AND_README:
        if not _blocks(page, "bash"):
            continue
        slow = page.name in SLOW_SHELL
        yield pytest.param(page, marks=(pytest.mark.slow,) if slow else (), id=page.name)


@pytest.mark.parametrize("page", list(_shell_pages()))
def test_the_shell_examples_run(page, tmp_path):
    """Every ```bash block of a page runs as written, in order, with ``set -e``, in an
    empty folder that holds only a link to the shipped ``datasets/`` (and ``studies/``):
    what a user types in a clone. ``ewb-ident`` is this interpreter's."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "ewb-ident"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m ewb_ident "$@"\n')
    shim.chmod(0o755)
    work = tmp_path / "work"
    work.mkdir()
    for name in ("datasets", "studies"):
        (work / name).symlink_to(ROOT / name)
    env = {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    for k, code in enumerate(_blocks(page, "bash")):
        script = SET_UP.sub("", code)
        proc = subprocess.run(
            ["bash", "-e", "-c", script], cwd=work, env=env, capture_output=True, text=True,
            timeout=3600,
        )  # fmt: skip
        # 3: done, but a fit outside the seed's acceptance (a concealed trace's baseline)
        assert proc.returncode in (0, 3), (
            f"{_rel(page)} bash block {k + 1} exited {proc.returncode}:\n{proc.stderr[-3000:]}"
        )


# --- synopses and files ------------------------------------------------------------------


def _options() -> dict[str, set[str]]:
    """Each command's options (and the global ones under ``""``), from the Typer app."""
    import typer

    from ewb_ident.cli import app

    group = typer.main.get_command(app)
    out = {"": {o for p in group.params for o in p.opts} | {"--help"}}
    for name, command in group.commands.items():
        out[name] = {o for p in command.params for o in [*p.opts, *p.secondary_opts]}
        out[name] |= {"--help"}
    return out


def _synopses():
    for page in PAGES_AND_README:
        for code in _blocks(page, ""):
            command = None
            for line in code.splitlines():
                if line.startswith("ewb-ident "):
                    words = [w for w in line.split()[1:] if not w.startswith("-")]
                    command = words[0] if words and words[0].islower() else ""
                elif not line.startswith(" "):
                    command = None
                if command is not None:
                    yield page, command, line


def test_every_synopsis_names_options_its_command_has():
    """A hand-written synopsis (``ewb-ident fit TRACE --out DIR [--stage ...]``) names
    only commands that exist and options they take."""
    options = _options()
    seen = 0
    bad = []
    for page, command, line in _synopses():
        seen += 1
        if command not in options:
            bad.append(f"{_rel(page)}: no command {command!r}: {line.strip()}")
            continue
        for flag in re.findall(r"(?<![\w-])--[a-z][a-z-]*", line):
            if flag not in options[command] | options[""]:
                bad.append(f"{_rel(page)}: `ewb-ident {command}` has no {flag}")
    assert seen >= 10
    assert not bad, "\n".join(bad)


def _toml_examples():
    """Each ```toml block with the shipped file it shows (named in backticks in the
    paragraph before it)."""
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for m in re.finditer(r"^```toml\n(.*?)^```", text, flags=re.S | re.M):
            before = text[: m.start()].rstrip().rsplit("\n\n", 1)[-1]
            named = re.findall(r"`((?:datasets|studies)/[\w/]+\.toml)`", before)
            assert named, f"{_rel(page)}: a TOML example names no shipped file before it"
            yield pytest.param(m.group(1), ROOT / named[-1], id=f"{page.name}:{named[-1]}")


@pytest.mark.parametrize(("code", "path"), list(_toml_examples()))
def test_toml_examples_are_the_shipped_files(code, path, tmp_path):
    """A TOML example shows (part of) the file it names, and the tool reads it: a
    column mapping through the mapping reader, a study through the study reader."""
    shown = tomllib.loads(code)
    shipped = tomllib.loads(path.read_text(encoding="utf-8"))
    for key, value in shown.items():
        assert shipped.get(key) == value, f"{path.name}: {key}"
    example = tmp_path / path.name
    example.write_text(code, encoding="utf-8")
    if path.parent.name == "studies":
        from ewb_ident.study import load_study

        load_study(example)
    else:
        from ewb_ident.data.units import load_mapping

        assert load_mapping(example)
