"""The product speaks of the software only: no words of how it was developed in the README, the changelog, the
docs, the code, the tests, the benchmarks or the examples (work sessions, issue numbers, who did what, a diary
cited as the source of a number)."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = ("neurogf_warp", "kernels", "tests", "benchmarks", "examples")
SUFFIXES = {".py", ".h", ".md", ".toml"}
SKIP_DIRS = {"__pycache__", ".pytest_cache"}  # caches are not product text

# Case-insensitive, word-bounded. Each names a process, not the software: a work session, an issue number, the
# people ("helper", "the lead"), a promise of a later measurement, and the retired diaries and an unshipped file.
PATTERNS = [re.compile(p, re.IGNORECASE) for p in (
    r"\bsessions?\b",
    r"\bissues? #?\d",
    r"\bhelpers?\b",
    r"\bthe lead\b",
    r"not yet measured",
    r"\bRESULTS\.md\b",
    r"\bgeodesics_notes\b",
    r"\bneurogf-reference\.md\b",
)]
# The only exception: pytest's own word for a fixture scope.
ALLOWED = [re.compile(r"""scope\s*=\s*["']session["']""")]
THIS_FILE = Path(__file__).resolve()  # it spells the patterns out


def product_files(root: Path = ROOT):
    """The text files the scan covers under ``root``: README.md, CHANGELOG.md, docs/**/*.md and the
    .py/.h/.md/.toml files of the package, kernel, test, benchmark and example folders."""
    files = [root / n for n in ("README.md", "CHANGELOG.md") if (root / n).is_file()]
    files += sorted((root / "docs").rglob("*.md")) if (root / "docs").is_dir() else []
    for folder in FOLDERS:
        if (root / folder).is_dir():
            files += sorted(p for p in (root / folder).rglob("*") if p.is_file() and p.suffix in SUFFIXES
                            and not SKIP_DIRS.intersection(p.relative_to(root).parts))
    return [p for p in files if p.resolve() != THIS_FILE]


def process_words(text: str):
    """(line number, matched text, line) for every process word in ``text`` outside the allowed uses."""
    hits = []
    for n, line in enumerate(text.splitlines(), 1):
        rest = line
        for allowed in ALLOWED:
            rest = allowed.sub("", rest)
        for pattern in PATTERNS:
            for m in pattern.finditer(rest):
                hits.append((n, m.group(0), line.strip()))
    return hits


def scan(files, root: Path = ROOT):
    """'path:line: word | line' for every hit in ``files``."""
    out = []
    for p in files:
        for n, word, line in process_words(p.read_text(encoding="utf-8", errors="replace")):
            out.append(f"{p.relative_to(root)}:{n}: {word!r} | {line[:120]}")
    return out


def test_the_product_has_no_words_of_the_development_process():
    hits = scan(product_files())
    assert not hits, f"{len(hits)} process words (say what the software does, and why, instead):\n" + "\n".join(hits)


# --- the scanner itself ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("line", [
    "# measured in the eleventh session", "Sessions of 2026", "see issue 24.5", "(issues 21, 22)", "Issue #7",
    "a helper found it", "two helpers", "asked the lead", "not yet measured on a GPU", "benchmarks/RESULTS.md",
    "see geodesics_notes.md", "docs/neurogf-reference.md section 9",
])
def test_the_scanner_finds_a_planted_word(line):
    assert process_words(f"x = 1\n{line}\n") and process_words(f"x = 1\n{line}\n")[0][0] == 2


@pytest.mark.parametrize("line", [
    '@pytest.fixture(scope="session")', "@pytest.fixture(scope='session', autouse=True)", "an issue with the mesh",
    "the leading dimensions", "lead = tuple(x.shape[:-1])", "results.json", "a reference solution",
])
def test_the_scanner_passes_ordinary_words(line):
    assert process_words(line) == []


def test_the_scan_covers_every_product_folder(tmp_path):
    for rel in ("README.md", "CHANGELOG.md", "docs/guide/a.md", "neurogf_warp/m.py", "kernels/native/k.h",
                "tests/t.py", "benchmarks/b.py", "benchmarks/README.md", "examples/e.py", "neurogf_warp/x.toml"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("ok\n# written in the third session\n")
    (tmp_path / "neurogf_warp/data.json").write_text('"session"\n')  # data, not text the scan reads
    (tmp_path / "notes.md").write_text("session\n")  # outside the product's places
    hits = scan(product_files(tmp_path), tmp_path)
    assert len(hits) == 10 and all(":2: 'session'" in h for h in hits)
