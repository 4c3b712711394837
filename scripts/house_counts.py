"""The counts issue 36 ("one typed view from the wire to the kernel") is judged by, measured on the source tree:

    python scripts/house_counts.py          # prints JSON; tests/repo/test_house_counts.py checks the same numbers

- render_query_declarations: classes that declare the render query's fields (annotated ``cam_to_ego``, ``fov`` and
  ``width``), and functions that re-declare them as parameters (ten or more of ViewQuery's fields: the route
  signature this replaced had 22);
- pose_matrix_parsers: functions that turn a pose's numbers into a 4x4 matrix (a ``reshape(4, 4)`` of input);
- output_format_lists: the lines that spell the render outputs or formats out (literal tuples, lists, Literals);
- stride_rules: the lines that compare a detail stride with its bounds (a literal 16 or DETAIL_STRIDE_MAX);
- any_fields_in_view_query: fields of common.wire.ViewQuery typed Any;
- runtime_import_cycles: cycles among runtime/'s modules (every import statement, a module's parents excepted);
- sys_path_edits: sys.path.insert / append / assignments in the repository's .py files."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CODE = ("common", "runtime", "server", "clients", "model_export")
SKIP = {".venv", "node_modules", ".git", "build"}


def _files(dirs=CODE):
    for d in dirs:
        for p in sorted((REPO / d).rglob("*.py")):
            if not SKIP & set(p.parts):
                yield p


def _trees(dirs=CODE):
    for p in _files(dirs):
        yield p, ast.parse(p.read_text())


def render_query_declarations() -> list[str]:
    out = []
    for p, tree in _trees():
        for node in ast.walk(tree):
            names = set()
            if isinstance(node, ast.ClassDef):
                names = {t.target.id for t in node.body if isinstance(t, ast.AnnAssign) and isinstance(t.target, ast.Name)}
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                args = {a.arg for a in node.args.args + node.args.kwonlyargs}
                names = args if len(args & _VIEW_FIELDS) >= 10 else set()
            if {"cam_to_ego", "fov", "width"} <= names:
                out.append(f"{p.relative_to(REPO)}:{node.lineno} {node.name}")
    return out


_VIEW_FIELDS = {"camera", "cam_to_ego", "fx", "fy", "cx", "cy", "fov", "distortion", "x", "y", "z", "pitch", "yaw",
                "roll", "forward", "left", "up", "width", "height", "output", "format", "quality"}


def pose_matrix_parsers() -> list[str]:
    out = []
    pat = re.compile(r"reshape\(\(?4,\s*4\)?\)")
    for p, tree in _trees():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and pat.search(ast.unparse(node)):
                inner = [n for n in ast.walk(node) if n is not node and isinstance(n, (ast.FunctionDef,))]
                if not any(pat.search(ast.unparse(n)) for n in inner):
                    out.append(f"{p.relative_to(REPO)}:{node.lineno} {node.name}")
    return out


def output_format_lists() -> list[str]:
    out = []
    for p, tree in _trees():
        for node in ast.walk(tree):
            elts = None
            if isinstance(node, (ast.Tuple, ast.List)):
                elts = node.elts
            elif isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == "Literal":
                elts = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
            if not elts:
                continue
            vals = {e.value for e in elts if isinstance(e, ast.Constant) and isinstance(e.value, str)}
            if vals >= {"rgb", "depth", "alpha"} or vals >= {"png", "jpeg", "exr"}:
                out.append(f"{p.relative_to(REPO)}:{node.lineno} {sorted(vals)}")
    return list(dict.fromkeys(out))     # a Literal is a subscript of a tuple: one line, counted once


def stride_rules() -> list[str]:
    out = []
    for p in _files():
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if "stride" in line and re.search(r"<=\s*(16|DETAIL_STRIDE_MAX)\b|\ble=16\b|\bin 1\.\.16\b", line):
                out.append(f"{p.relative_to(REPO)}:{i}")
    return out


def any_fields_in_view_query() -> list[str]:
    from xyzcyl.common.wire import ViewQuery

    return [name for name, f in ViewQuery.model_fields.items() if "Any" in str(f.annotation)]


def import_cycles(folder: str = "runtime", package: str = "xyzcyl.runtime") -> list[list[str]]:
    root = REPO / folder
    mods = {}
    for p in root.rglob("*.py"):
        parts = [x for x in p.relative_to(root).with_suffix("").parts if x != "__init__"]
        mods[".".join([package, *parts])] = p
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, p in mods.items():
        base = m.split(".") if p.name == "__init__.py" else m.split(".")[:-1]
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom):
                mod = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else [])) \
                    if node.level else (node.module or "")
                targets = [mod, *(f"{mod}.{a.name}" for a in node.names)]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            graph[m] |= {t for t in targets if t in mods and t != m and not m.startswith(t + ".")}
    # strongly connected components of more than one module (Tarjan, iterative enough for a package's size)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def sys_path_edits() -> list[str]:
    out = []
    pat = re.compile(r"sys\.path\.(insert|append|extend)\(|sys\.path\s*(\+)?=|sys\.path\[")
    for p in sorted(REPO.rglob("*.py")):
        if SKIP & set(p.relative_to(REPO).parts) or p.name == "house_counts.py":
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if pat.search(line):
                out.append(f"{p.relative_to(REPO)}:{i}")
    return out


def counts() -> dict:
    items = {"render_query_declarations": render_query_declarations(), "pose_matrix_parsers": pose_matrix_parsers(),
             "output_format_lists": output_format_lists(), "stride_rules": stride_rules(),
             "any_fields_in_view_query": any_fields_in_view_query(), "runtime_import_cycles": import_cycles(),
             "sys_path_edits": sys_path_edits()}
    return {k: {"count": len(v), "where": v} for k, v in items.items()}


if __name__ == "__main__":
    print(json.dumps(counts(), indent=1))
