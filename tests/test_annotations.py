"""Every public function and method of the package says in type hints what it takes and gives (STYLE: "type hints
on public functions"): a reader of a stage function or a concept module sees a parameter's kind without reading
its callers. Public means reachable without an underscore: a top-level function or a method of a public class,
not a function nested in another. Exempt: the Triton kernels (`render/_kernels.py`, whose parameters Triton reads
as `tl.constexpr` or pointers), `self`/`cls`, and the return of dunder methods (`__init__` returns None)."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "diffshadow"
EXEMPT_FILES = {"render/_kernels.py"}


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def unannotated(source: str) -> list[str]:
    """`'line name: what'` for each public function or method in `source` lacking a parameter's or its return's
    hint."""
    found = []

    def visit(node: ast.AST, public: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                visit(child, public and not is_private(child.name))
            elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                if public and not is_private(child.name):
                    a = child.args
                    missing = [p.arg for p in a.posonlyargs + a.args + a.kwonlyargs
                               if p.annotation is None and p.arg not in ("self", "cls")]
                    missing += [f"*{p.arg}" for p in (a.vararg,) if p is not None and p.annotation is None]
                    missing += [f"**{p.arg}" for p in (a.kwarg,) if p is not None and p.annotation is None]
                    if child.returns is None and not child.name.startswith("__"):
                        missing.append("return")
                    if missing:
                        found.append(f"{child.lineno} {child.name}: {', '.join(missing)}")
                # a function's own nested functions are not public API
            elif not isinstance(child, ast.Lambda):
                visit(child, public)

    visit(ast.parse(source), True)
    return found


def test_the_check_sees_what_it_should():
    source = '''
def f(a, b: int): ...
def g(a: int): ...
def _h(a): ...
def k(*args, **kwargs) -> None: ...
class C:
    def __init__(self, x): ...
    def m(self, y: int) -> int:
        def inner(z): ...
    def _n(self, q): ...
class _D:
    def m(self, y): ...
if True:
    def under_if(a) -> None: ...
'''
    assert unannotated(source) == ["2 f: a, return", "3 g: return", "5 k: *args, **kwargs", "7 __init__: x",
                                   "14 under_if: a"]


def test_every_public_function_is_annotated():
    missing = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel not in EXEMPT_FILES and (found := unannotated(path.read_text())):
            missing[rel] = found
    assert not missing, "public functions without type hints:\n" + "\n".join(
        f"diffshadow/{rel}:{line}" for rel, lines in missing.items() for line in lines)
