"""No module of riskplan or its Hydra plugins patches Hydra: nothing assigns to or deletes anything reached through
a name imported from hydra, and a module that imports hydra calls no setattr()/delattr() (the way a patch reaches
a class it holds in a variable). Hydra is used through its plugins (hydra_plugins/) and its API."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def hydra_names(tree: ast.Module) -> set[str]:
    """The local names a module binds to hydra's modules, classes and functions."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {(a.asname or a.name).split(".")[0] for a in node.names if a.name.split(".")[0] == "hydra"}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "hydra":
            names |= {a.asname or a.name for a in node.names}
    return names


def root(node: ast.AST) -> str | None:
    while isinstance(node, (ast.Attribute, ast.Subscript)):
        node = node.value
    return node.id if isinstance(node, ast.Name) else None


def patches(source: str) -> list[int]:
    """Lines that patch Hydra: `X.attr = ...` or `del X.attr` with X from a hydra import, and in a module that
    imports hydra any setattr() or delattr()."""
    tree = ast.parse(source)
    hydra = hydra_names(tree)
    lines = set()
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
        elif isinstance(node, ast.Delete):
            targets = node.targets
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("setattr", "delattr"):
            if hydra:
                lines.add(node.lineno)
        if any(isinstance(t, ast.Attribute) and root(t) in hydra for t in targets):
            lines.add(node.lineno)
    return sorted(lines)


def test_the_scan_finds_each_kind_of_patch():
    source = (
        "from hydra._internal.hydra import Hydra\n"
        "import hydra.core.utils as utils\n"
        "Hydra.get_mode = lambda *a: None\n"
        "setattr(Hydra, 'run', None)\n"
        "del utils.run_job\n"
        "x = Hydra\n"  # a plain use
        "other.attr = 1\n"  # not hydra's
        "for owner in [x]:\n"
        "    setattr(owner, 'get_mode', None)\n"  # a class held in a variable
    )
    assert patches(source) == [3, 4, 5, 9]
    assert patches("class A:\n    pass\nsetattr(A, 'b', 1)\nA.c = 2\n") == []  # no hydra here


def test_no_module_patches_hydra():
    found = {}
    for path in sorted([*(ROOT / "riskplan").rglob("*.py"), *(ROOT / "hydra_plugins").rglob("*.py")]):
        text = path.read_text()
        if "hydra" not in text:  # no hydra import, so no name to patch through (and most modules): skip the parse
            continue
        lines = patches(text)
        if lines:
            found[str(path.relative_to(ROOT))] = lines
    assert found == {}
