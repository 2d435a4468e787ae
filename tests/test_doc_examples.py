"""Every code example of the README and the docs runs as written.

Fenced ```python blocks run in order, one shared namespace per markdown file. The working directory is a
temporary stand-in for the checkout's root (links to the checkout's files, the shared test data beside it as
``../shared``), so the text's paths resolve as they do from a checkout, and what a block writes stays out of it.

```bash blocks: every ``neurogf-warp``, ``python -m neurogf_warp...`` and ``torchrun ... -m neurogf_warp...``
command must parse with its command's own parser, and every ``python some/script.py`` must name a file of the
checkout. A bash block preceded by ``<!-- run -->`` is run, in-process, and each of its commands must exit with 0.

A block preceded by ``<!-- no-run: REASON -->`` (needs a GPU, a long training run) is reported as skipped with
that reason.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import os
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import SHARED, shared_path

pytestmark = pytest.mark.slow  # the blocks load released models, train a smoke model and compile a user kernel

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
FENCE = re.compile(r"^(\s*)(```+|~~~+)\s*([\w+-]*)")
NO_RUN = re.compile(r"^\s*<!--\s*no-run:\s*(.+?)\s*-->\s*$")
RUN = re.compile(r"^\s*<!--\s*run\s*-->\s*$")
PYTHON = ("python", "py", "pycon")
SHELL = ("bash", "sh", "shell", "console")


@dataclass
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    skip: str | None  # the no-run reason
    run: bool  # a bash block marked <!-- run -->

    @property
    def name(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks_of(page: Path) -> list[Block]:
    """The fenced code blocks of a markdown page, with the marker comment on the line before each (if any)."""
    lines = page.read_text(encoding="utf-8").splitlines()
    out, i, before = [], 0, ""
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            if lines[i].strip():
                before = lines[i]
            i += 1
            continue
        indent, fence, lang = len(m.group(1)), m.group(2), m.group(3).lower()
        start, body = i, []
        i += 1
        while i < len(lines) and not lines[i].strip().startswith(fence):
            body.append(lines[i][indent:] if lines[i][:indent].strip() == "" else lines[i])
            i += 1
        if i == len(lines):
            raise ValueError(f"{page}:{start + 1}: code block never closed")
        i += 1
        skip = NO_RUN.match(before)
        out.append(Block(page, start + 1, lang, "\n".join(body) + "\n", skip.group(1) if skip else None,
                         bool(RUN.match(before))))
        before = ""
    return out


BLOCKS = {page: blocks_of(page) for page in PAGES}
RUNNABLE = [b for page in PAGES for b in BLOCKS[page] if b.lang in PYTHON or (b.lang in SHELL and b.run)]


# ---- running the blocks of a page in order ----------------------------------------------------------------------

class PageRun:
    """One page's namespace and working directory; blocks run in order, each at most once."""

    def __init__(self, page: Path, root: Path):
        self.page = page
        self.cwd = root / "checkout"
        self.cwd.mkdir(parents=True)
        (root / "shared").symlink_to(SHARED, target_is_directory=True)
        # the checkout's own files (examples/, docs/, ...) as seen from its root; what a block writes stays here
        for entry in ROOT.iterdir():
            if not entry.name.startswith(".") and not entry.name.endswith(".egg-info"):
                (self.cwd / entry.name).symlink_to(entry, target_is_directory=entry.is_dir())
        self.sources = root / "blocks"
        self.sources.mkdir()
        self.ns = {"__name__": "doc_example_" + re.sub(r"\W", "_", str(page.relative_to(ROOT)).removesuffix(".md"))}
        self.done: set[int] = set()
        self.failed: Block | None = None

    def run_upto(self, block: Block) -> None:
        for b in BLOCKS[self.page]:
            if b.line > block.line:
                break
            if b not in RUNNABLE or b.line in self.done or b.skip:
                continue
            if self.failed is not None:
                pytest.skip(f"an earlier block of this page failed: {self.failed.name}")
            self.done.add(b.line)
            try:
                with _chdir(self.cwd):
                    self._python(b) if b.lang in PYTHON else self._shell(b)
            except BaseException:
                self.failed = b
                raise

    def _python(self, b: Block) -> None:
        # a real file, so that Warp (and tracebacks) can read the source of kernels the block defines
        src = self.sources / f"line{b.line}.py"
        src.write_text(b.code, encoding="utf-8")
        exec(compile(b.code, str(src), "exec"), self.ns)  # noqa: S102

    def _shell(self, b: Block) -> None:
        from neurogf_warp.cli.main import main

        for argv in commands(b.code):
            assert argv[0] == "neurogf-warp", f"{b.name}: a run block may only hold neurogf-warp commands: {argv}"
            rc = main(argv[1:])
            assert rc == 0, f"{b.name}: {shlex.join(argv)} exited with {rc}"


@contextlib.contextmanager
def _chdir(path: Path):
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


@pytest.fixture(scope="module")
def page_runs(tmp_path_factory):
    runs: dict[Path, PageRun] = {}

    def get(page: Path) -> PageRun:
        if page not in runs:
            shared_path("checkpoints", "official")  # skips (fails under CI) without the shared data
            runs[page] = PageRun(page, tmp_path_factory.mktemp(page.stem))
        return runs[page]

    return get


@pytest.mark.parametrize("block", RUNNABLE, ids=[b.name for b in RUNNABLE])
def test_the_example_runs_as_written(block: Block, page_runs):
    if block.skip:
        pytest.skip(block.skip)
    page_runs(block.page).run_upto(block)


# ---- commands in bash blocks --------------------------------------------------------------------------------------

def commands(code: str) -> list[list[str]]:
    """The commands of a shell block: continuation lines joined, comments dropped, ``a && b`` split."""
    joined = re.sub(r"\\\n", " ", code)
    out = []
    for line in joined.splitlines():
        words = shlex.split(line, comments=True)
        while words:
            cut = words.index("&&") if "&&" in words else len(words)
            if words[:cut]:
                out.append(words[:cut])
            words = words[cut + 1:]
    return out


class _Parsed(BaseException):  # not an Exception: a command's own "except Exception" must not catch it
    pass


def _parse_only(self, args=None, namespace=None):
    ns = _ORIGINAL_PARSE(self, args, namespace)
    raise _Parsed(ns)


_ORIGINAL_PARSE = argparse.ArgumentParser.parse_args


def check_parses(argv: list[str], where: str) -> None:
    """Parse one command line with the parser of the command it names, running nothing."""
    if argv[0] == "torchrun":
        if "--no-python" in argv:
            argv = argv[argv.index("--no-python") + 1:]
            while argv and argv[0].startswith("-"):  # a torchrun option after --no-python
                argv = argv[2:] if "=" not in argv[0] else argv[1:]
        else:
            assert "-m" in argv, f"{where}: torchrun without -m or --no-python: {shlex.join(argv)}"
            argv = ["python"] + argv[argv.index("-m"):]
    if argv[0] == "neurogf-warp":
        from neurogf_warp.cli.main import main as entry

        call = lambda: entry(argv[1:])  # noqa: E731
    elif argv[:2] == ["python", "-m"] and argv[2].split(".")[0] == "neurogf_warp":
        module = importlib.import_module(argv[2])
        assert hasattr(module, "main"), f"{where}: {argv[2]} has no main()"
        call = lambda: module.main(argv[3:])  # noqa: E731
    else:
        pytest.fail(f"{where}: not a command of this package: {shlex.join(argv)}")
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            call()
    except _Parsed:
        return
    except SystemExit as e:  # -h exits 0; an argparse error exits 2 and says why
        assert e.code in (0, None), f"{where}: {shlex.join(argv)} does not parse:\n{err.getvalue()}"
        return
    pytest.fail(f"{where}: {shlex.join(argv)} never reached its argument parser")


SHELL_PAGES = [p for p in PAGES if any(b.lang in SHELL for b in BLOCKS[p])]


@pytest.mark.parametrize("page", SHELL_PAGES, ids=[str(p.relative_to(ROOT)) for p in SHELL_PAGES])
def test_the_commands_parse(page: Path, monkeypatch):
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", _parse_only)
    for b in BLOCKS[page]:
        if b.lang not in SHELL:
            continue
        for argv in commands(b.code):
            if argv[0] == "python" and len(argv) > 1 and argv[1].endswith(".py"):
                assert (ROOT / argv[1]).is_file(), f"{b.name}: {argv[1]} is not a file of the checkout"
                continue
            if argv[0] in ("neurogf-warp", "torchrun") or (
                    argv[:2] == ["python", "-m"] and argv[2].startswith("neurogf_warp.")):
                check_parses(argv, b.name)


def test_the_examples_are_found():
    """The extraction itself: the README has Python examples and a run block, and every guide has examples."""
    readme = BLOCKS[ROOT / "README.md"]
    assert any(b.lang in PYTHON and not b.skip for b in readme)
    assert any(b.lang in SHELL and b.run for b in readme)
    guides = sorted((ROOT / "docs" / "guides").glob("*.md"))
    assert guides
    for g in guides:
        assert BLOCKS[g], f"{g.name} has no code block"
    assert commands("a x \\\n  y # note\nb && c z") == [["a", "x", "y"], ["b"], ["c", "z"]]
