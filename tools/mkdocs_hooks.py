"""MkDocs hooks of the documentation site (``mkdocs.yml``: ``hooks:``).

Three things the pages in ``docs/`` cannot hold by themselves:

* **The command-line reference** (``docs/cli.md``) is rendered from the command line
  itself: every command of ``ewb-ident``, its description, a table of its arguments and
  options, and its ``--help`` as the terminal prints it. It cannot fall behind the code.
* **The benchmarks page** (``docs/benchmarks.md``) holds every generated
  ``reports/bench_*.md`` (what ``python -m benchmarks.bench_*`` last wrote).
* **Files of the repository outside ``docs/``** that a page links to (the README, the
  changelog, a study's report and its figures) are published under ``repo/`` with the
  same path, and the links to them are rewritten to point there. A link from a page of
  ``docs/`` reads the same on the site and in a clone (``../README.md``).

A page holds ``<!-- generated: NAME -->`` where the hook puts generated text.
"""

from __future__ import annotations

import io
import posixpath
import re
from contextlib import redirect_stdout
from pathlib import Path

from mkdocs.structure.files import File, Files, InclusionLevel

ROOT = Path(__file__).resolve().parents[1]
#: Where files of the repository outside ``docs/`` appear on the site.
MOUNT = "repo/"
#: Markdown inline links and images: ``[text](target)``, ``![alt](target "title")``.
LINK = re.compile(r"(!?\[[^\]]*\]\()([^)\s]+)((?:\s+\"[^\"]*\")?\))")
FENCE = re.compile(r"^(```|~~~)")
EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:|^#|^/", re.I)
MARKER = re.compile(r"<!-- generated: ([a-z-]+) -->")


# --- links to the repository outside docs/ --------------------------------------------


def _repo_path(page_src_uri: str) -> str:
    """The repository path of a site page: ``docs/X`` for a page of ``docs/``, ``P`` for
    a file published under :data:`MOUNT`."""
    if page_src_uri.startswith(MOUNT):
        return page_src_uri[len(MOUNT) :]
    return "docs/" + page_src_uri


def _site_uri(repo_path: str) -> str:
    if repo_path.startswith("docs/"):
        return repo_path[len("docs/") :]
    return MOUNT + repo_path


def _targets(markdown: str, repo_path: str):
    """Each relative link of a page outside code blocks: (match, repository path of the
    target, its ``#fragment``)."""
    out = []
    fenced = False
    offset = 0
    for line in markdown.splitlines(keepends=True):
        if FENCE.match(line.lstrip()):
            fenced = not fenced
        elif not fenced:
            for m in LINK.finditer(line):
                target = m.group(2)
                if EXTERNAL.match(target):
                    continue
                path, _, frag = target.partition("#")
                resolved = posixpath.normpath(posixpath.join(posixpath.dirname(repo_path), path))
                out.append((offset + m.start(), m, resolved, frag))
        offset += len(line)
    return out


def _mounted(start: list[str]) -> set[str]:
    """Files of the repository outside ``docs/`` that pages link to, and what the linked
    Markdown files link to in turn."""
    seen: set[str] = set()
    todo = list(start)
    while todo:
        repo_path = todo.pop()
        text = (ROOT / repo_path).read_text(encoding="utf-8")
        for _, _, target, _ in _targets(text, repo_path):
            if target.startswith(("docs/", "../")) or target in seen:
                continue
            if not (ROOT / target).is_file():
                continue  # MkDocs reports the broken link on the page itself
            seen.add(target)
            if target.endswith(".md"):
                todo.append(target)
    return seen


def on_files(files: Files, config) -> Files:
    pages = [f"docs/{f.src_uri}" for f in files.documentation_pages()]
    for repo_path in sorted(_mounted(pages)):
        path = str(ROOT / repo_path)
        # Reached by links; the README and the changelog are in the nav as well.
        level = InclusionLevel.NOT_IN_NAV
        files.append(File.generated(config, MOUNT + repo_path, abs_src_path=path, inclusion=level))
    return files


def _rewrite_links(markdown: str, src_uri: str) -> str:
    repo_path = _repo_path(src_uri)
    here = posixpath.dirname(src_uri)
    pieces = []
    last = 0
    for start, m, target, frag in _targets(markdown, repo_path):
        if not (ROOT / target).exists():
            continue  # MkDocs reports it as written
        site = _site_uri(target)
        new = posixpath.relpath(site, here or ".") + (f"#{frag}" if frag else "")
        pieces.append(markdown[last : start + m.start(2) - m.start()])
        pieces.append(new)
        last = start + m.end(2) - m.start()
    pieces.append(markdown[last:])
    return "".join(pieces)


# --- generated pages --------------------------------------------------------------------


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def cli_reference() -> str:
    """Markdown of every ``ewb-ident`` command, read from the Typer app."""
    import typer
    from typer.testing import CliRunner

    from ewb_ident.cli import app

    group = typer.main.get_command(app)
    runner = CliRunner()

    def help_text(args: list[str]) -> str:
        out = runner.invoke(app, [*args, "--help"], prog_name="ewb-ident", env={"COLUMNS": "96"})
        assert out.exit_code == 0, out.output
        return "\n".join(line.rstrip() for line in out.output.strip("\n").splitlines())

    def table(command) -> list[str]:
        # Read by duck typing: Typer's parameters are Click's or, in newer Typers, a
        # copy of Click's of its own.
        rows = ["| argument or option | default | what |", "|---|---|---|"]
        for p in command.params:
            if p.param_type_name == "argument":
                name = f"`{p.name.upper()}`" + (" ..." if p.nargs == -1 else "")
            else:
                name = ", ".join(f"`{o}`" for o in [*p.opts, *p.secondary_opts])
            if p.required:
                default = "required"
            elif p.default is None or p.default is False or p.default == ():
                default = ""
            else:
                default = f"`{p.default}`"
            rows.append(f"| {name} | {default} | {_cell(p.help or '')} |")
        return rows

    lines = [
        f"`ewb-ident --help`: {_cell(group.help.split(chr(10))[0])}",
        "",
        *table(group),
        "",
        "```text",
        help_text([]),
        "```",
    ]
    for name, command in group.commands.items():
        lines += [
            "",
            f"## ewb-ident {name}",
            "",
            _cell((command.help or "").strip()),
            "",
            *table(command),
            "",
            f'??? note "`ewb-ident {name} --help`"',
            "",
            "    ```text",
            *[f"    {line}" if line else "" for line in help_text([name]).splitlines()],
            "    ```",
        ]
    return "\n".join(lines) + "\n"


def benchmark_reports() -> str:
    """Every ``reports/bench_*.md``, its headings one level down, under a heading of its
    file name."""
    lines = []
    for path in sorted((ROOT / "reports").glob("bench_*.md")):
        text = path.read_text(encoding="utf-8")
        fenced = False
        body = []
        for line in text.splitlines():
            if FENCE.match(line.lstrip()):
                fenced = not fenced
            body.append("##" + line if line.startswith("#") and not fenced else line)
        lines += [f"## {path.stem}", "", f"`reports/{path.name}`", "", *body, ""]
    return "\n".join(lines)


GENERATED = {"cli-reference": cli_reference, "benchmark-reports": benchmark_reports}


def on_page_markdown(markdown: str, page, config, files) -> str:
    def fill(m: re.Match) -> str:
        with redirect_stdout(io.StringIO()):
            return GENERATED[m.group(1)]()

    markdown = MARKER.sub(fill, markdown)
    if page.file.src_uri.startswith(MOUNT):
        markdown = _plain_brackets(markdown)
    return _rewrite_links(markdown, page.file.src_uri)


BRACKETS = re.compile(r"(?<![!\\])\[([^\]\[]*)\](?![(:])")
CODE_SPAN = re.compile(r"(`+).*?\1")


def _plain_brackets(markdown: str) -> str:
    """Brackets that are not a link, escaped: a generated report's ``[tanh(...)] [V]``
    (a unit after an expression) is text, not a reference link to an anchor ``V``."""
    out = []
    fenced = False
    for line in markdown.splitlines(keepends=True):
        if FENCE.match(line.lstrip()):
            fenced = not fenced
        if fenced or FENCE.match(line.lstrip()):
            out.append(line)
            continue
        pieces, last = [], 0
        for m in CODE_SPAN.finditer(line):
            pieces.append(BRACKETS.sub(r"\\[\1\\]", line[last : m.start()]))
            pieces.append(m.group(0))
            last = m.end()
        pieces.append(BRACKETS.sub(r"\\[\1\\]", line[last:]))
        out.append("".join(pieces))
    return "".join(out)
