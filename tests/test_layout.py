"""The package's layout is its pipeline: each layer imports only the layers below it.

    cli → study → reporting → diagnosis → inference → mechanisms → model → runtime → data
    rig → data        (the synthetic rig; only the CLI and the study runner use it)

``runtime`` (compiled programs, their disk store, threads, the process's set-up) sits
under the model: the layers above ask it for compiled programs and threads, and it
imports nothing of theirs.

``ewb_ident/__init__.py`` is the public façade and may import anything. No module imports
a private name (``_x``) from another module. These are read from the source with
:mod:`ast`, so the test needs no import of the package.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "ewb_ident"
LAYERS = [
    "data", "runtime", "model", "mechanisms", "inference", "diagnosis", "reporting", "study",
    "cli",
]  # fmt: skip
#: Modules over the size the layout aims for (~600 lines), each with the line count it
#: had when this list was written: a listed module may shrink but not grow, and no new
#: module may pass the limit.
MAX_LINES = 600
OVER = {
    "ewb_ident.diagnosis.discovery": 688,
    "ewb_ident.diagnosis.diagnose": 803,
    "ewb_ident.study": 718,
    "ewb_ident.reporting.html": 629,
    "ewb_ident.rig.simulate": 664,
    "ewb_ident.data.readers": 643,
    "ewb_ident.data.validation": 633,
    "ewb_ident.diagnosis.inputs": 601,
}


def _modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out.append((".".join(parts), path))
    return out


def _layer(module: str) -> str | None:
    """The layer (first folder) of a module; ``None`` for the façade and ``__main__``."""
    parts = module.split(".")
    if len(parts) < 2 or parts[1] == "__main__":
        return None
    return parts[1]


def _type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def _imports(module: str, path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, absolute module, imported names) of every run-time import in a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and _type_checking(node):
            for sub in node.body:
                for inner in ast.walk(sub):
                    skip.add(id(inner))
    out = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names = [a.name for a in node.names]
            if target.startswith("ewb_ident"):
                # ``from ewb_ident.x import y`` may import the module ``x.y``
                sub = [f"{target}.{n}" for n in names if (PACKAGE.parent / Path(
                    *f"{target}.{n}".split("."))).with_suffix(".py").exists()]
                out.append((node.lineno, target, names))
                out.extend((node.lineno, s, []) for s in sub)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("ewb_ident"):
                    out.append((node.lineno, a.name, []))
    return out


MODULES = _modules()


def _rank(layer: str | None) -> int | None:
    return LAYERS.index(layer) if layer in LAYERS else None


@pytest.mark.parametrize("module,path", MODULES, ids=[m for m, _ in MODULES])
def test_imports_follow_the_layers(module, path):
    own = _layer(module)
    if own is None:  # the façade and __main__
        return
    bad = []
    for line, target, _ in _imports(module, path):
        other = _layer(target)
        if other is None or other == own:
            continue
        if own == "rig":
            ok = other == "data"
        elif other == "rig":
            ok = own in ("cli", "study")
        else:
            ok = _rank(other) is not None and _rank(own) is not None and _rank(other) < _rank(own)
        if not ok:
            bad.append(f"{path.name}:{line} imports {target}")
    assert not bad, f"{module} ({own}) reaches up or sideways: " + "; ".join(bad)


@pytest.mark.parametrize("module,path", MODULES, ids=[m for m, _ in MODULES])
def test_no_private_name_crosses_a_module(module, path):
    bad = [
        f"{path.name}:{line} imports {n} from {target}"
        for line, target, names in _imports(module, path)
        for n in names
        if n.startswith("_") and target != module
    ]
    assert not bad, "; ".join(bad)


def test_the_runtime_sits_under_the_model():
    """The compiled programs, their disk store, the threads and the process's set-up are
    one layer, directly under the model: model, inference and diagnosis import it; it
    imports nothing above it, not even the façade (of the layer below, only the atomic
    writes of ``data.outputs``, so that an interrupted command removes half-written cache
    files too); and the model layer no longer holds the program cache."""
    assert LAYERS.index("runtime") == LAYERS.index("data") + 1 == LAYERS.index("model") - 1
    runtime = [(m, p) for m, p in MODULES if _layer(m) == "runtime"]
    assert {m.rsplit(".", 1)[-1] for m, _ in runtime} >= {"programs", "store", "threads", "config"}
    outside = {
        f"{p.name}:{line} imports {target}"
        for m, p in runtime
        for line, target, _ in _imports(m, p)
        if _layer(target) != "runtime" and target != "ewb_ident.data.outputs"
    }
    assert not outside, "; ".join(sorted(outside))
    users = {
        _layer(m)
        for m, p in MODULES
        for _, target, _ in _imports(m, p)
        if _layer(target) == "runtime" and _layer(m) != "runtime"
    }
    assert {"model", "inference", "diagnosis"} <= users, users
    assert not (PACKAGE / "model" / "programs.py").exists()


def test_layers_are_folders():
    for layer in LAYERS + ["rig", "mechanisms"]:
        if layer == "study":
            assert (PACKAGE / "study.py").exists()
        else:
            assert (PACKAGE / layer / "__init__.py").exists(), layer
    loose = sorted(
        p.name for p in PACKAGE.glob("*.py") if p.name not in ("__init__.py", "__main__.py",
                                                               "study.py")
    )
    assert not loose, f"modules outside the layers: {loose}"


def test_the_facade_resolves_every_public_name():
    """Was: after the move into folders, ``ewb_ident.fit`` (the README's Python example)
    looked for ``ewb_ident.least_squares`` and raised; the lazy façade names each
    name's module, and the static imports for type checkers name the same objects."""
    import ewb_ident

    tree = ast.parse((PACKAGE / "__init__.py").read_text(encoding="utf-8"))
    static = {
        a.asname or a.name: node.module
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("ewb_ident.")
        for a in node.names
    }
    assert set(static) == set(ewb_ident.__all__)
    for name in ewb_ident.__all__:
        module = __import__(static[name], fromlist=[name])
        assert getattr(ewb_ident, name) is getattr(module, name), name


def test_no_commit_hash_or_machine_diary_in_readme_package_or_tests():
    """The README, docstrings and tests say what and why, not when or where: no commit
    hash (a 7-12 character token of hex digits and letters) and no diary of which
    N-core machine a figure came from. History belongs in CHANGELOG.md, measurements in
    generated reports."""
    import re

    root = PACKAGE.parent
    files = [root / "README.md", *PACKAGE.rglob("*.py"), *(root / "tests").rglob("*.py")]
    commit = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,12}\b")
    machine = re.compile(r"\bthe \d+-core machine\b|\b(faster|slower) machine\b", re.I)
    bad = []
    for path in files:
        for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            if commit.search(line) or machine.search(line):
                bad.append(f"{path.relative_to(root)}:{k}: {line.strip()[:80]}")
    assert not bad, "\n".join(bad)


def test_no_module_grows_past_the_size_the_layout_aims_for():
    """A module over MAX_LINES lines is one of OVER and no longer than it was listed."""
    for name, path in _modules():
        n = len(path.read_text(encoding="utf-8").splitlines())
        assert n <= OVER.get(name, MAX_LINES), f"{name}: {n} lines; split it"


def test_validation_rigs_stand_apart_and_nothing_edits_sys_path():
    """The independent rigs are a package of their own (``validation_rigs/``, installed
    beside the tool): the tool never imports them, and the tests, studies and benchmarks
    reach them, and each other, by imports (``from studies import ...``), never by
    editing ``sys.path``."""
    root = PACKAGE.parent
    rigs = root / "validation_rigs"
    names = {"other_rig", "third_rig", "uncatalogued_rig"}
    assert {p.stem for p in rigs.glob("*.py")} >= names
    for folder in ("tests", "studies", "benchmarks"):
        assert (root / folder / "__init__.py").exists(), folder
        assert not [n for n in names if (root / folder / f"{n}.py").exists()], folder
    reach = [
        f"{p.relative_to(root)}: imports validation_rigs"
        for p in PACKAGE.rglob("*.py")
        if "validation_rigs" in p.read_text(encoding="utf-8")
    ]
    edits = [
        f"{p.relative_to(root)}:{k + 1}"
        for folder in ("tests", "studies", "benchmarks", "validation_rigs")
        for p in sorted((root / folder).rglob("*.py"))
        for k, line in enumerate(p.read_text(encoding="utf-8").splitlines())
        if "sys.path." in line and p.name != "test_layout.py"
    ]
    assert not reach and not edits, reach + edits
