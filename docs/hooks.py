"""The command-line reference, generated from the ``neurogf-warp`` argparse parsers, and the MkDocs hook that keeps
the committed page current.

    python docs/hooks.py            # rewrite docs/reference/cli.md from the parsers
    python docs/hooks.py --check    # exit 1 when docs/reference/cli.md differs from what the parsers give

``mkdocs build`` runs the same check (``on_pre_build``) and fails a strict build on a stale page, so a changed
option or help text cannot reach the site without its reference.
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from pathlib import Path

PAGE = Path(__file__).resolve().parent / "reference" / "cli.md"
PROG = "neurogf-warp"
WIDTH = 100  # argparse wraps usage lines to the terminal; a fixed width keeps the page the same on every machine

EXIT_CODES = """\
## Exit codes

| code | meaning |
| --- | --- |
| 0 | success |
| 1 | a failure that is not the input's fault: a full disk, a device error, or an internal error (the message says what to report) |
| 2 | bad input: an unknown option, a missing or unreadable file, a value out of range, a mesh that does not match the model; the message names the option |
| 130 | interrupted (Ctrl-C); `train` says where its checkpoint is, and running the same command again continues |

`gen-per-mesh` also exits 1 when training failed for any mesh of the folder (the others are kept).
Errors are one line on stderr; `--verbose`, or the environment variable `NEUROGF_DEBUG=1`, shows the traceback
instead.
"""


class _Captured(Exception):
    def __init__(self, parser):
        super().__init__("parser captured")
        self.parser = parser


def _parser_of(run) -> argparse.ArgumentParser:
    """The parser that the entry point ``run(argv)`` builds, taken at its first ``parse_args`` (nothing runs)."""
    original = argparse.ArgumentParser.parse_args

    def capture(self, *args, **kwargs):
        raise _Captured(self)

    argparse.ArgumentParser.parse_args = capture
    try:
        run([])
    except _Captured as c:
        return c.parser
    finally:
        argparse.ArgumentParser.parse_args = original
    raise RuntimeError(f"{run!r} built no argparse parser")


def _commands():
    """[(name, one-line summary, parser)] of every command, in the order of ``neurogf-warp -h``."""
    from neurogf_warp.cli.main import build_parser

    top = build_parser()
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
    summary = {c.dest: c.help for c in sub._choices_actions}
    out = [(name, summary.get(name) or "", parser) for name, parser in sub.choices.items()]
    try:  # commands dispatched before the main parser runs, each with a parser of its own
        from neurogf_warp.generalizable.hooks import CLI_COMMANDS
    except ImportError:
        CLI_COMMANDS = {}
    seen = {name: i for i, (name, _, _) in enumerate(out)}
    for name, run in CLI_COMMANDS.items():
        parser = _parser_of(run)
        line = summary.get(name) or (parser.description or "").split(". ")[0].rstrip(".")
        if name in seen:
            out[seen[name]] = (name, line, parser)
        else:
            out.append((name, line, parser))
    return top, out


def _option_name(action) -> str:
    if not action.option_strings:
        return f"`{action.metavar or action.dest}`"
    names = ", ".join(f"`{s}`" for s in action.option_strings)
    if action.nargs == 0:
        return names
    mv = action.metavar
    if isinstance(mv, tuple):
        mv = " ".join(m for m in mv if m)
    if mv is None and action.choices and not isinstance(action.choices, dict):
        mv = "{" + ",".join(map(str, action.choices)) + "}"
    mv = mv or action.dest.upper()
    if action.nargs in ("+", "*"):
        mv = f"{mv} ..."
    elif isinstance(action.nargs, int) and action.nargs > 1 and not isinstance(action.metavar, tuple):
        mv = " ".join([mv] * action.nargs)
    return f"{names} `{mv}`"


def _cell(text) -> str:
    return " ".join(str(text or "").split()).replace("|", "\\|")


def _usage(parser, prog: str) -> str:
    parser.prog = prog
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(WIDTH + 2)
    try:
        return parser.format_usage().strip()
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


def _arguments(parser, skip=(), only=None):
    rows = []
    for a in parser._actions:
        if isinstance(a, (argparse._HelpAction, argparse._VersionAction)) or a.dest in skip or a.help == argparse.SUPPRESS:
            continue
        if only is not None and a.dest not in only:
            continue
        text = _cell(a.help)
        if a.required and a.option_strings:
            text = f"{text} (required)".strip()
        rows.append(f"| {_option_name(a)} | {text} |")
    return rows


def render() -> str:
    """The whole page, as Markdown."""
    top, commands = _commands()
    builtin = [p for n, _, p in commands if not n.startswith("gen-")]
    common = set.intersection(*({a.dest for a in p._actions if a.option_strings} for p in builtin)) - {"help"}
    lines = [
        "# Command line",
        "",
        "<!-- generated by `python docs/hooks.py` from the argparse parsers; do not edit by hand -->",
        "",
        _cell(top.description),
        "",
        "```text",
        _usage(top, PROG),
        "```",
        "",
        "| command | what it does |",
        "| --- | --- |",
    ]
    lines += [f"| [`{n}`](#{n}) | {_cell(s)} |" for n, s, _ in commands]
    lines += ["", "`neurogf-warp --version` prints the version; `neurogf-warp COMMAND -h` a command's options.", ""]
    some = builtin[0]
    lines += ["## Options of every command", "",
              "Every command except the `gen-*` ones takes these options.", "",
              "| option | meaning |", "| --- | --- |"]
    lines += _arguments(some, only=common)
    lines.append("")
    for name, summary, parser in commands:
        skip = common if not name.startswith("gen-") else set()
        lines += [f"## {name}", "", _cell(parser.description or summary), "", "```text",
                  _usage(parser, f"{PROG} {name}"), "```", ""]
        rows = _arguments(parser, skip=skip)
        if rows:
            lines += ["| argument | meaning |", "| --- | --- |", *rows, ""]
    lines.append(EXIT_CODES)
    return "\n".join(lines).rstrip() + "\n"


# ------------------------------------------------------------------------------------------------- MkDocs hook

log = logging.getLogger("mkdocs.plugins.neurogf_cli")


def on_pre_build(config, **kwargs):
    """Warn (a failure under ``--strict``) when the committed CLI page is not what the parsers give."""
    with contextlib.redirect_stdout(sys.stderr):
        page = render()
    if not PAGE.is_file() or PAGE.read_text(encoding="utf-8") != page:
        log.warning("docs/reference/cli.md is out of date with the command line's parsers: run "
                    "'python docs/hooks.py' and commit the page")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="write (or --check) docs/reference/cli.md from the CLI parsers")
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 when the page is out of date")
    a = ap.parse_args(argv)
    page = render()
    if a.check:
        current = PAGE.read_text(encoding="utf-8") if PAGE.is_file() else ""
        if current != page:
            print(f"{PAGE} is out of date: run 'python docs/hooks.py'", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(page, encoding="utf-8")
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
