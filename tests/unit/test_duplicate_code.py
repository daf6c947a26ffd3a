"""No function of the product written twice: the same body (its docstring aside) under two names or in
two modules, which the text-based duplicate scanner misses when the copies' layout differs.

What a review of the tree once found that way: ``describe()`` ten times, ``_say`` three times, the
takeover block in three services; this check found a frame's label twice. A body small enough to be an idiom (under
``MIN_NODES`` AST nodes: a one-line getter, ``return None``) is not counted.
"""
from __future__ import annotations

import ast
import hashlib
from collections import defaultdict

from tests.tools import REPO

MIN_NODES = 25  # a body this many AST nodes or larger is code, not an idiom


def function_bodies(root=REPO) -> dict[str, list[str]]:
    """Hash of each function's arguments and body (docstring dropped) -> where it is defined."""
    out: dict[str, list[str]] = defaultdict(list)
    for folder in ("quick_stream", "services"):
        for path in sorted((root / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                body = node.body
                if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                        and isinstance(body[0].value.value, str):
                    body = body[1:]
                if sum(1 for b in body for _ in ast.walk(b)) < MIN_NODES:
                    continue
                text = ast.dump(node.args) + "".join(ast.dump(b) for b in body)
                out[hashlib.sha1(text.encode()).hexdigest()].append(
                    f"{path.relative_to(root)}:{node.lineno} {node.name}")
    return out


def test_no_function_body_is_written_twice():
    twice = [where for where in function_bodies().values() if len(where) > 1]
    assert twice == [], "\n".join(", ".join(w) for w in twice)


def test_the_check_finds_a_copy(tmp_path):
    (tmp_path / "services").mkdir()
    pkg = tmp_path / "quick_stream"
    pkg.mkdir()
    body = "    total = 0\n    for x in xs:\n        if x > 0:\n            total += x * x\n    return total / len(xs)\n"
    (pkg / "a.py").write_text(f"def mean_square(xs):\n    '''one'''\n{body}")
    (pkg / "b.py").write_text(f"def positive_energy(xs):\n{body}")
    assert [w for w in function_bodies(tmp_path).values() if len(w) > 1] == [
        ["quick_stream/a.py:1 mean_square", "quick_stream/b.py:1 positive_energy"]]
