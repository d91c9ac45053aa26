"""Every assertion in the suite can fail: a static (AST) check of all test files.

It fails on

* ``assert <call of a numpy.testing assert_* function>``: those return None, so such an ``assert``
  fails even when the arrays agree; and ``assert_allclose(a, b) and x == y`` never checks ``x == y``
  (None is false, so ``and`` stops there), with or without the ``assert`` keyword;
* an expression statement that is a boolean operation containing an ``assert_*`` call (the same
  mistake without the ``assert`` keyword);
* ``assert <constant>`` (``assert True``, ``assert 1``, ``assert "text"``) and ``assert (cond, "msg")``
  (a non-empty tuple is always true);
* a test function with no check at all: no ``assert``, no ``pytest.raises``/``warns``/``fail``/``approx``,
  no ``assert_*`` call and no call of a helper of the same module that checks something (or of a
  function whose name starts with ``assert``, ``_assert``, ``check`` or ``verify``).

``EXCEPTIONS`` lists test functions allowed to have no check, each with the reason.
"""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent

#: "path::function" -> why it has no explicit check
EXCEPTIONS: dict[str, str] = {}

CHECK_PREFIXES = ("assert", "_assert", "check", "_check", "verify", "_verify")


def _call_name(node: ast.AST) -> str | None:
    if isinstance(node, ast.Call):
        f = node.func
        if isinstance(f, ast.Name):
            return f.id
        if isinstance(f, ast.Attribute):
            return f.attr
    return None


def _is_assert_call(node: ast.AST) -> bool:
    name = _call_name(node)
    return name is not None and name.startswith("assert_")


def _contains_assert_call(node: ast.AST) -> bool:
    return any(_is_assert_call(n) for n in ast.walk(node))


def _has_check(fn: ast.AST, checking_helpers: set[str]) -> bool:
    for n in ast.walk(fn):
        if isinstance(n, ast.Assert):
            return True
        name = _call_name(n)
        if name is None:
            continue
        if name in ("raises", "warns", "fail", "approx", "deprecated_call") or name.startswith(CHECK_PREFIXES):
            return True
        if name in checking_helpers:
            return True
    return False


def problems_in(path: Path) -> list[str]:
    """Dead or missing assertions in one test file, as ``path:line: message``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    rel = path.relative_to(TESTS.parent)
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Assert):
            t = n.test
            if _is_assert_call(t):
                out.append(f"{rel}:{n.lineno}: assert of an assert_* call (it returns None)")
            elif isinstance(t, ast.BoolOp) and any(_contains_assert_call(v) for v in t.values):
                out.append(f"{rel}:{n.lineno}: assert_* call inside and/or: the other operand is never checked")
            elif isinstance(t, ast.Constant):
                out.append(f"{rel}:{n.lineno}: assert of a constant ({t.value!r})")
            elif isinstance(t, ast.Tuple) and t.elts:
                out.append(f"{rel}:{n.lineno}: assert of a non-empty tuple (always true)")
        elif isinstance(n, ast.Expr) and isinstance(n.value, ast.BoolOp):
            if any(_contains_assert_call(v) for v in n.value.values):
                out.append(f"{rel}:{n.lineno}: assert_* call inside and/or: the other operand is never checked")
    # helpers of this module that check something (one level of indirection, iterated to a fixed point)
    funcs = {f.name: f for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))}
    checking: set[str] = set()
    changed = True
    while changed:
        changed = False
        for name, f in funcs.items():
            if name not in checking and not name.startswith("test") and _has_check(f, checking):
                checking.add(name)
                changed = True
    for name, f in funcs.items():
        if name.startswith("test") and not _has_check(f, checking):
            key = f"{rel}::{name}"
            if key not in EXCEPTIONS:
                out.append(f"{rel}:{f.lineno}: test {name} checks nothing (no assert, raises or assert_* call)")
    return out


def _test_files() -> list[Path]:
    return sorted(p for p in TESTS.rglob("test_*.py") if "__pycache__" not in p.parts)


def test_no_assertion_that_cannot_fail():
    files = _test_files()
    assert len(files) > 20
    problems = [p for f in files for p in problems_in(f)]
    assert problems == [], "\n".join(problems)


def test_the_checker_finds_planted_dead_assertions():
    """The checker itself can fail: each planted pattern is reported, a checking helper is recognised."""
    src = (
        "from numpy.testing import assert_allclose\n"  # 1
        "def test_a():\n    assert_allclose(1, 1) and 1 == 2\n"  # 2, 3
        "def test_b():\n    assert assert_allclose(1, 1) or True\n"  # 4, 5
        "def test_c():\n    assert True\n"  # 6, 7
        "def test_d():\n    assert (1 == 2, 'message')\n"  # 8, 9
        "def test_e():\n    x = 1 + 1\n"  # 10, 11
        "def _helper():\n    assert 1 == 1\n"  # 12, 13
        "def test_f():\n    _helper()\n"  # 14, 15
        "def test_g():\n    assert assert_allclose(1, 1)\n"  # 16, 17
    )
    found = problems_in_text(src, "planted.py")
    joined = "\n".join(found)
    assert "planted.py:3: assert_* call inside and/or" in joined
    assert "planted.py:5: assert_* call inside and/or" in joined
    assert "planted.py:7: assert of a constant (True)" in joined
    assert "planted.py:9: assert of a non-empty tuple" in joined
    assert "planted.py:10: test test_e checks nothing" in joined
    assert "planted.py:17: assert of an assert_* call" in joined
    assert "test_f" not in joined  # the helper checks
    assert len(found) == 6, joined


def problems_in_text(text: str, name: str) -> list[str]:
    """:func:`problems_in` on source text (for the self-test), reported under ``name``."""
    import tempfile

    with tempfile.TemporaryDirectory(dir=TESTS) as d:
        p = Path(d) / name
        p.write_text(text)
        rel = str(p.relative_to(TESTS.parent))
        return [line.replace(rel, name) for line in problems_in(p)]
