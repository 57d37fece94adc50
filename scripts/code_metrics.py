"""Structural limits of the package's source: module, function and class size,
returned tuples, import cycles and imports that go up the layers.

``python scripts/code_metrics.py`` prints every breach; ``tests/test_code_metrics.py``
fails on any.  A function's size counts every line of its body but the docstring (comments and
blank lines included); a class's, its lines of code (no docstrings, comments or
blanks); a module's, every line.
"""

from __future__ import annotations

import ast
import io
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

MAX_MODULE_LINES = 500
MAX_FUNCTION_CODE_LINES = 60
MAX_CLASS_CODE_LINES = 200
MAX_RETURNED_TUPLE = 3
#: parameters of a function (self excepted); more take a dataclass.  Compiled
#: kernels (names ending in ``_py``, made by ``util.lazy_numba``) are exempt:
#: numba takes flat arrays.
MAX_PARAMETERS = 10

#: layers from the bottom up; a module may import only its own layer and those before it
LAYERS = ["errors", "util", "model", "physics", "geometry", "io", "pipeline", "sim", "calib",
          "viz", "cli"]
#: top-level modules of mems_stereo that sit outside the layers (the package's face)
FACADE = {"mems_stereo", "mems_stereo.__main__", "mems_stereo.data", "mems_stereo.presets"}


def package_modules():
    """(dotted name, path) of every module of mems_stereo, calib/ and viz/."""
    return list(_package_modules())


def _package_modules():
    for folder, prefix in ((ROOT / "mems_stereo", "mems_stereo"),
                           (ROOT / "calib", "mems_stereo.calib"),
                           (ROOT / "viz", "mems_stereo.viz")):
        for p in sorted(folder.rglob("*.py")):
            rel = p.relative_to(folder).with_suffix("").parts
            name = ".".join((prefix, *rel)).removesuffix(".__init__")
            yield name, p


def _code_lines(source: str) -> set[int]:
    """Line numbers that hold code (tokens other than comments and newlines)."""
    lines: set[int] = set()
    skip = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
            tokenize.DEDENT, tokenize.ENCODING, tokenize.ENDMARKER}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type not in skip:
            lines.update(range(tok.start[0], tok.end[0] + 1))
    return lines


def _docstring_lines(node) -> set[int]:
    body = getattr(node, "body", None)
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        return set(range(body[0].lineno, body[0].end_lineno + 1))
    return set()


def _all_docstring_lines(nodes) -> set[int]:
    out: set[int] = set()
    for node in nodes:
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            out |= _docstring_lines(node)
    return out


def _resolve(name: str, path: Path, node: ast.ImportFrom) -> str | None:
    """The absolute module an ImportFrom names (relative imports resolved)."""
    if node.level == 0:
        return node.module
    pkg = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    base = pkg[: len(pkg) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(name: str, path: Path, nodes=None, known: set[str] | None = None) -> set[str]:
    """Every mems_stereo module this module imports (module level and in functions)."""
    nodes = nodes if nodes is not None else list(ast.walk(ast.parse(path.read_text())))
    known = known if known is not None else {n for n, _ in package_modules()}
    out: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(name, path, node)
            if base is None:
                continue
            # `from pkg import mod` imports the submodule mod when there is one
            mods = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base
                    for a in node.names]
        else:
            continue
        for m in mods:
            while m and m not in known and "." in m:
                m = m.rsplit(".", 1)[0]
            if m in known and m != name:
                out.add(m)
    return out


def _layer(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else None


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(10000)

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _private_names(all_nodes) -> set[str]:
    """Private names the package defines: functions, classes, module constants and
    instance attributes (``self._x = ...``) whose names start with one underscore."""
    out: set[str] = set()
    for nodes in all_nodes:
        for node in nodes:
            if isinstance(node, ast.FunctionDef | ast.ClassDef | ast.AsyncFunctionDef):
                out.add(node.name)
            elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) \
                    and isinstance(node.value, ast.Name) and node.value.id == "self":
                out.add(node.attr)
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                out.add(node.id)
    return {n for n in out if n.startswith("_") and not n.startswith("__")}


def _is_package_init(name: str) -> bool:
    return (ROOT / "mems_stereo" / Path(*name.split(".")[1:]) / "__init__.py").exists() \
        or name in ("mems_stereo.calib", "mems_stereo.viz")


def breaches() -> dict[str, list[str]]:
    """Every breach of the limits, by kind."""
    out: dict[str, list[str]] = {k: [] for k in (
        "module size", "function size", "class size", "returned tuple",
        "import cycle", "layer", "deprecated module", "parameters", "private name")}
    modules = list(package_modules())
    known = {n for n, _ in modules}
    sources = {name: path.read_text() for name, path in modules}
    walked = {name: list(ast.walk(ast.parse(src))) for name, src in sources.items()}
    private = _private_names(walked.values())
    graph: dict[str, set[str]] = {}
    for name, path in modules:
        src = sources[name]
        nodes = walked[name]
        rel = path.relative_to(ROOT)
        n_lines = src.count("\n")
        if n_lines > MAX_MODULE_LINES:
            out["module size"].append(f"{rel}: {n_lines} lines")
        if "deprecated" in path.stem:
            out["deprecated module"].append(str(rel))
        code = _code_lines(src) - _all_docstring_lines(nodes)
        for node in nodes:
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                if isinstance(node, ast.ClassDef):  # code lines (no docstrings, comments)
                    n = len(set(range(node.lineno, node.end_lineno + 1)) & code)
                else:  # every line of the body but the docstring
                    body = node.body[1:] if _docstring_lines(node) else node.body
                    first = body[0].lineno if body else node.end_lineno + 1
                    n = node.end_lineno - first + 1
                if isinstance(node, ast.ClassDef) and n > MAX_CLASS_CODE_LINES:
                    out["class size"].append(f"{rel}:{node.lineno} {node.name}: {n}")
                elif not isinstance(node, ast.ClassDef) and n > MAX_FUNCTION_CODE_LINES:
                    out["function size"].append(f"{rel}:{node.lineno} {node.name}: {n}")
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) \
                    and not node.name.endswith("_py"):
                a = node.args
                n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
                n -= bool(a.args and a.args[0].arg in ("self", "cls"))
                if n > MAX_PARAMETERS:
                    out["parameters"].append(f"{rel}:{node.lineno} {node.name}: {n}")
            if isinstance(node, ast.Attribute) and node.attr in private \
                    and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                out["private name"].append(f"{rel}:{node.lineno} {ast.unparse(node)}")
            if isinstance(node, ast.ImportFrom):
                base = _resolve(name, path, node)
                if base and base.startswith("mems_stereo"):
                    for al in node.names:
                        if al.name.startswith("_") and not al.name.startswith("__") \
                                and f"{base}.{al.name}" not in known:
                            out["private name"].append(
                                f"{rel}:{node.lineno} from {base} import {al.name}")
            if isinstance(node, ast.Call) and ast.unparse(node.func).endswith("import_module") \
                    and node.args and isinstance(node.args[0], ast.Constant) \
                    and str(node.args[0].value).startswith("mems_stereo."):
                target = str(node.args[0].value)
                if _layer(name) in LAYERS and _layer(target) in LAYERS \
                        and LAYERS.index(_layer(target)) > LAYERS.index(_layer(name)):
                    out["layer"].append(f"{name} imports {target} (import_module)")
            if isinstance(node, ast.Return) and isinstance(node.value, ast.Tuple) \
                    and len(node.value.elts) > MAX_RETURNED_TUPLE:
                out["returned tuple"].append(
                    f"{rel}:{node.lineno}: {len(node.value.elts)} elements")
        deps = imports_of(name, path, nodes, known)
        # a package's __init__ re-exports its own modules: an edge down into
        # the package is not a cycle of the design
        graph[name] = {d for d in deps
                       if not (_is_package_init(d) and name.startswith(d + "."))}
        me = _layer(name)
        if me in LAYERS:
            for d in deps:
                other = _layer(d)
                if other in LAYERS and LAYERS.index(other) > LAYERS.index(me):
                    out["layer"].append(f"{name} imports {d}")
    out["import cycle"] = [" <-> ".join(c) for c in _cycles(graph)]
    return out


def main() -> int:
    found = breaches()
    total = 0
    for kind, items in found.items():
        print(f"{kind}: {len(items)}")
        for it in items:
            print(f"    {it}")
        total += len(items)
    return 1 if total else 0


if __name__ == "__main__":
    raise SystemExit(main())
