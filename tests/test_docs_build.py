"""The documentation site: the command-line reference matches the parsers, and the site builds without a warning."""
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "docs" / "hooks.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_cli_reference_is_current():
    hooks = _hooks()
    page = (ROOT / "docs" / "reference" / "cli.md").read_text(encoding="utf-8")
    assert page == hooks.render(), "docs/reference/cli.md is out of date: run 'python docs/hooks.py'"


def test_cli_reference_lists_every_command_and_exit_code():
    page = (ROOT / "docs" / "reference" / "cli.md").read_text(encoding="utf-8")
    hooks = _hooks()
    _, commands = hooks._commands()
    for name, _, parser in commands:
        assert f"\n## {name}\n" in page, name
        for action in parser._actions:
            for flag in action.option_strings:
                if flag not in ("-h", "--help"):
                    assert f"`{flag}`" in page, (name, flag)
    for code in ("| 0 |", "| 1 |", "| 2 |", "| 130 |"):
        assert code in page


@pytest.mark.slow
def test_site_builds_strict(tmp_path):
    for module in ("mkdocs", "mkdocstrings_handlers.python", "material"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} is not installed: pip install -e '.[docs]'")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
