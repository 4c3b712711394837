"""No Python file of the repository edits sys.path (issue 36): the package is imported as installed, the
benchmark scripts import a sibling script as a script's folder is on the path (pytest: pyproject's pythonpath).
The code is read (ast), so a docstring or comment that names such an edit is not one."""

from __future__ import annotations

import ast
import subprocess

from xyzcyl.testing import REPO

MUTATORS = {"insert", "append", "extend", "remove", "pop", "clear"}
SKIP = ("docs/runs/",)      # records of past runs, not code


def _is_sys_path(node: ast.AST) -> bool:
    return (isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name)
            and node.value.id == "sys")


def edits(source: str) -> list[int]:
    """The lines of ``source`` that change sys.path: a call of a list method on it, an assignment to it or to a
    slice of it (augmented too), a deletion from it."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        targets: list[ast.AST] = []
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in MUTATORS:
            targets = [node.func.value]
        elif isinstance(node, ast.Assign | ast.Delete):
            targets = node.targets
        elif isinstance(node, ast.AugAssign | ast.AnnAssign):
            targets = [node.target]
        if any(_is_sys_path(t) or (isinstance(t, ast.Subscript) and _is_sys_path(t.value)) for t in targets):
            lines.append(node.lineno)
    return lines


def _python_files() -> list[str]:
    """The repository's .py files: tracked, or new and not ignored (git; .venv and other ignored folders out)."""
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "--", "*.py"], cwd=REPO,
                         capture_output=True, text=True, check=True, timeout=60).stdout
    return sorted({f for f in out.splitlines() if not f.startswith(SKIP) and (REPO / f).is_file()})


def test_the_reader_finds_edits_and_only_them():
    p = "sys" + ".path"         # not spelled out, for readers that grep
    for code in ("{}.insert(0, x)", "{}.append(x)", "{}[:0] = [x]", "{} += [x]", "{} = [x]", "del {}[0]",
                 "def f():\n    {}.extend(y)"):
        assert edits(code.format(p)), code
    for code in ("print({})", "x = {}[0]", "x in {}", "'{}.insert(0, x)'", "# {}.append(x)", "a.path.insert(0, x)"):
        assert not edits(code.format(p)), code


def test_no_file_edits_sys_path():
    files = _python_files()
    assert "cli.py" in files and len(files) > 100
    bad = []
    for f in files:
        text = (REPO / f).read_text(errors="replace")
        if "sys" + ".path" not in text:      # only these can hold an edit (as it is written)
            continue
        try:
            bad += [f"{f}:{n}" for n in edits(text)]
        except SyntaxError as e:             # a file being written: its own tests say so
            print(f"{f}: not read ({e})")
    assert bad == []
