"""Module and function sizes of the package (lines), for the layout notes in RESULTS.md.

    python benchmarks/code_sizes.py [ROOT] [--json out.json]

Counts every .py file under ROOT/neurogf_warp and ROOT/kernels (and the native header): lines per module, per
stage folder, and the longest functions (ast, decorators excluded).
"""
from __future__ import annotations

import argparse
import ast
import json
from pathlib import Path


def sizes(root: Path) -> dict:
    mods, funcs = {}, []
    for top in ("neurogf_warp", "kernels"):
        for f in sorted((root / top).rglob("*")):
            if f.suffix not in (".py", ".h") or "__pycache__" in f.parts:
                continue
            rel = f.relative_to(root).as_posix()
            text = f.read_text()
            mods[rel] = text.count("\n")
            if f.suffix == ".py":
                for node in ast.walk(ast.parse(text)):
                    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                        funcs.append((node.end_lineno - node.lineno + 1, f"{rel}:{node.name}"))
    folders = {}
    for rel, n in mods.items():
        folder = rel.rsplit("/", 1)[0]
        folders[folder] = folders.get(folder, 0) + n
    funcs.sort(reverse=True)
    return {"modules": mods, "folders": folders, "n_modules": len(mods), "lines": sum(mods.values()),
            "longest_functions": funcs[:15], "functions_over_60_lines": sum(1 for n, _ in funcs if n > 60)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", nargs="?", default=str(Path(__file__).resolve().parents[1]))
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    s = sizes(Path(a.root))
    print(f"{s['n_modules']} files, {s['lines']} lines; functions over 60 lines: {s['functions_over_60_lines']}")
    for folder, n in sorted(s["folders"].items()):
        print(f"  {folder:<40} {n:>6}")
    print("longest functions:")
    for n, name in s["longest_functions"]:
        print(f"  {n:>4}  {name}")
    if a.json:
        Path(a.json).write_text(json.dumps(s, indent=1))


if __name__ == "__main__":
    main()
