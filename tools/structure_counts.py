#!/usr/bin/env python
"""Counts behind the structure of the checkout: lines of Python per package (the library's
agents/ against the application's evflow_cli/), functions longer than a limit, and the places
an option of the window size is declared (a dataclass field named ``window_size`` or an
``add_argument("--window-size" | "--dt")``).

    python tools/structure_counts.py            # this checkout
    python tools/structure_counts.py --long 60 --list
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("agents", "evflow_cli", "envs", "losses", "scripts")
WINDOW_FLAGS = {"--window-size", "--dt"}


def python_files(package: str) -> list[Path]:
    return sorted(p for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)


def lines(paths: list[Path]) -> int:
    return sum(len(p.read_text().splitlines()) for p in paths)


def long_functions(paths: list[Path], limit: int) -> list[tuple[int, str]]:
    found = []
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > limit:
                    found.append((length, f"{path.relative_to(ROOT)}:{node.name}"))
    return sorted(found, reverse=True)


def window_size_declarations(paths: list[Path]) -> list[str]:
    """Option declarations of the window size: class-level ``window_size: ...`` fields of
    dataclasses and ``add_argument`` calls naming --window-size or --dt."""
    found = []
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef):
                found += [f"{path.relative_to(ROOT)}:{item.lineno} {node.name}.window_size" for item in node.body
                          if isinstance(item, ast.AnnAssign) and getattr(item.target, "id", None) == "window_size"]
            elif isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument":
                flags = {a.value for a in node.args if isinstance(a, ast.Constant)}
                if flags & WINDOW_FLAGS:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} add_argument({', '.join(sorted(flags))})")
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--long", type=int, default=60, help="a function longer than this many lines is long")
    parser.add_argument("--list", action="store_true", help="list the long functions and the declarations")
    args = parser.parse_args()
    files = {package: python_files(package) for package in PACKAGES}
    for package, paths in files.items():
        print(f"{package + '/':12s} {lines(paths):6d} lines in {len(paths)} files")
    every = [p for paths in files.values() for p in paths]
    long = long_functions(every, args.long)
    declared = window_size_declarations(every)
    print(f"functions over {args.long} lines: {len(long)}")
    print(f"window_size option declarations: {len(declared)}")
    if args.list:
        for length, name in long:
            print(f"  {length:4d}  {name}")
        for place in declared:
            print(f"  {place}")


if __name__ == "__main__":
    main()
