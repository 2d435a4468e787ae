"""The installed package carries every file the code reads at run time (a non-editable install has only what
pyproject.toml lists)."""
import fnmatch
import pathlib

import tomllib

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_every_data_file_is_in_package_data():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs, data = cfg["package-dir"], cfg.get("package-data", {})
    missing = []
    for package in cfg["packages"]:
        top = next(p for p in sorted(dirs, key=len, reverse=True) if package == p or package.startswith(p + "."))
        folder = ROOT / dirs[top] / package[len(top):].lstrip(".").replace(".", "/")
        sub = {q for q in cfg["packages"] if q.startswith(package + ".")}
        for f in folder.rglob("*"):
            rel = f.relative_to(folder).as_posix()
            if not f.is_file() or f.suffix in (".py", ".pyc") or "__pycache__" in rel:
                continue
            if any(f.is_relative_to(ROOT / dirs[top] / q[len(top):].lstrip(".").replace(".", "/")) for q in sub):
                continue  # belongs to a subpackage, checked there
            if not any(fnmatch.fnmatch(rel, g) for g in data.get(package, [])):
                missing.append(f"{package}: {rel}")
    assert not missing, f"files not installed by pyproject.toml's package-data: {missing}"
