"""The package keeps its functions readable: none over 80 lines, none with more than 8
parameters (self/cls not counted) — issue #27's limits, checked on every run."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dualflow", "retarget", "sim", "ros_free_bridge", "firmware_cfg")
MAX_LINES, MAX_PARAMS = 80, 8


def _functions():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    a = node.args
                    n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + bool(a.vararg) + bool(a.kwarg)
                    if a.args and a.args[0].arg in ("self", "cls"):
                        n -= 1
                    where = f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"
                    yield where, node.end_lineno - node.lineno + 1, n


def test_no_function_is_longer_than_80_lines():
    long = [f"{w} ({n} lines)" for w, n, _ in _functions() if n > MAX_LINES]
    assert not long, "split these functions: " + ", ".join(long)


def test_no_function_takes_more_than_8_parameters():
    wide = [f"{w} ({p} parameters)" for w, _, p in _functions() if p > MAX_PARAMS]
    assert not wide, "group these parameters (a small dataclass): " + ", ".join(wide)


def test_the_check_sees_the_whole_package():
    # a wrong root would find nothing and pass vacuously
    assert sum(1 for _ in _functions()) > 1000
