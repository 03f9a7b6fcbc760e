"""The package's layers point one way: every `import` of a diffshadow module (at the top, inside a function or
under TYPE_CHECKING alike) goes to a module of its own layer or a lower one, and the import graph has no circle.
docs/architecture.md draws the same layers."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "diffshadow"

# lowest first; a module's layer is that of its longest listed prefix
LAYERS = [
    # foundations
    ["diffshadow", "phases", "config", "io", "stopping", "progress", "transfer", "metrics", "capacity", "analytic",
     "hpc", "graphs", "adam"],
    ["volume", "layout", "siren", "lights", "sampling", "grid", "store", "codecs"],  # data
    ["shadow", "truth"],  # ground truth
    ["data_inr"],
    ["render"],  # the renderer, its fused kernels included
    ["seams", "fit"],  # stage 1
    ["diffusion", "correction"],  # stage 2, and the correction of stage 1's blend (the model's light encoding)
    ["evaluate", "caches", "report", "summary", "scaling"],
    ["artifacts", "runtime", "argparsing", "stages", "bench", "parsl_fit", "viewer"],  # files, processes, stages
    ["cli"],
]


def module_names() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        found |= {t for t in targets if t in known and t != name}
    return found


def graph() -> dict[str, set[str]]:
    names = module_names()
    return {name: imports(name, path, set(names)) for name, path in names.items()}


def layer(name: str) -> int | None:
    """The module's layer (its longest listed prefix), None where none is listed."""
    short = name.removeprefix("diffshadow.") if name != "diffshadow" else name
    best = None
    for i, members in enumerate(LAYERS):
        for m in members:
            if (short == m or short.startswith(m + ".")) and (best is None or len(m) > len(best[1])):
                best = (i, m)
    return None if best is None else best[0]


def test_every_module_has_a_layer():
    unplaced = sorted(name for name in graph() if layer(name) is None)
    assert not unplaced, f"in no layer of tests/test_layers.py (add each where it belongs): {unplaced}"
    assert layer("diffshadow.nowhere") is None


def test_no_import_runs_up_a_layer():
    upward = sorted(f"{a} (layer {layer(a)}) imports {b} (layer {layer(b)})"
                    for a, deps in graph().items() for b in deps if layer(b) > layer(a))
    assert not upward, "\n".join(upward)


def find_circle(g: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(g[n]):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (found := visit(m)):
                return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(g):
        if n not in state and (found := visit(n)):
            return found
    return None


def test_no_import_circle():
    circle = find_circle(graph())
    assert circle is None, " -> ".join(circle)


def test_the_checks_can_fail():
    """A circle and an upward import are found when there is one (so the tests above are not vacuous)."""
    assert find_circle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert layer("diffshadow.fit") > layer("diffshadow.lights")
    path = PACKAGE / "lights.py"
    assert "diffshadow.io" in imports("diffshadow.lights", path, set(module_names()))
