"""The command line's help: every command listed, every option explained, numbers finite, presets as described."""
import argparse
import re

import pytest

from neurogf_warp.cli import main as cli
from neurogf_warp.cli.gen import GEN_COMMANDS


def _subparsers(parser):
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def _gen_parser(name, monkeypatch):
    """The parser that ``neurogf-warp NAME`` builds (caught when it starts parsing)."""
    seen = {}

    def catch(self, args=None, namespace=None):
        seen["parser"] = self
        raise SystemExit(0)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", catch)
    with pytest.raises(SystemExit):
        cli.main([name, "-h"])
    monkeypatch.undo()
    return seen["parser"]


def all_parsers(monkeypatch):
    """{command: its parser} for every command, the gen-* ones with the parsers they really use."""
    subs = dict(_subparsers(cli.build_parser()))
    for name in GEN_COMMANDS:
        subs[name] = _gen_parser(name, monkeypatch)
    return subs


def test_top_level_help_lists_every_command_with_a_line(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["-h"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    names = set(_subparsers(cli.build_parser()))
    assert set(GEN_COMMANDS) <= names and {"train", "render", "info"} <= names
    for name in names:
        line = re.search(rf"^\s+{re.escape(name)}\s*\n?\s+(\S.*)$", text, re.M)
        assert line and len(line.group(1)) > 10, f"{name} is not listed with a description in -h"


def test_every_option_of_every_command_has_help(monkeypatch):
    missing = []
    for name, parser in all_parsers(monkeypatch).items():
        if name in GEN_COMMANDS:
            assert parser.prog == f"neurogf-warp {name}", parser.prog  # not `python -m ...`
        for action in parser._actions:
            if not action.help or action.help == argparse.SUPPRESS:
                missing.append(f"{name} {'/'.join(action.option_strings) or action.dest}")
    assert not missing, f"options without help: {missing}"


def test_gen_commands_print_their_usage_under_this_program(capsys):
    for name in GEN_COMMANDS:
        with pytest.raises(SystemExit) as e:
            cli.main([name, "-h"])
        out = capsys.readouterr().out
        assert e.value.code == 0 and out.startswith(f"usage: neurogf-warp {name} "), out[:80]
        assert "python -m" not in out
        if name != "gen-shapes":  # the line that runs it on several GPUs
            assert f"torchrun --nproc_per_node N --no-python neurogf-warp {name} FOLDER" in " ".join(out.split())


def test_no_numeric_option_takes_nan_or_inf(monkeypatch):
    """Every option that converts text to a number refuses nan and inf (argparse then exits 2 naming it)."""
    takes = []
    for name, parser in all_parsers(monkeypatch).items():
        for action in parser._actions:
            if action.type is None:
                continue
            for text in ("nan", "inf", "-inf"):
                try:
                    value = action.type(text)
                except (ValueError, TypeError, argparse.ArgumentTypeError):
                    continue
                if isinstance(value, float):
                    takes.append(f"{name} {'/'.join(action.option_strings)} {text}")
    assert not takes, f"non-finite numbers accepted: {takes}"


@pytest.mark.parametrize("argv, flag", [
    (["render", "m.ngf", "-o", "x.png", "--view", "nan", "0"], "--view"),
    (["render", "m.ngf", "-o", "x.png", "--view", "0", "inf"], "--view"),
    (["render", "m.ngf", "-o", "x.png", "--vrange", "0", "inf"], "--vrange"),
    (["ssad", "m.ngf", "--point", "0", "nan", "0"], "--point"),
    (["train", "mesh.obj", "-o", "m.ngf", "--lr", "nan"], "--lr"),
    (["demo", "--budget-seconds", "inf"], "--budget-seconds"),
    (["gen-train", "coll", "-o", "g.pt", "--lr-min", "nan"], "--lr-min"),
    (["gen-train", "coll", "-o", "g.pt", "--budget-seconds", "inf"], "--budget-seconds"),
    (["gen-per-mesh", "coll", "-o", "out", "--budget-seconds", "nan"], "--budget-seconds"),
])
def test_non_finite_numbers_are_refused_naming_the_argument(argv, flag, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and flag in err and "finite" in err, err


@pytest.mark.parametrize("values", [["nan", "0", "0"], ["0", "inf", "0"]])
def test_non_finite_points_are_refused_before_the_model_is_read(values, tmp_path, capsys):
    code = cli.main(["distance", str(tmp_path / "missing.ngf"), "--p", *values, "--q", "0", "0", "0"])
    err = capsys.readouterr().err
    assert code == 2 and "--p" in err and "finite" in err, err


def test_non_finite_points_in_a_file_are_refused(tmp_path, capsys):
    import numpy as np

    np.save(tmp_path / "p.npy", np.array([[0.0, 0, 0], [0, np.nan, 0]]))
    code = cli.main(["path", str(tmp_path / "missing.ngf"), "--p", str(tmp_path / "p.npy"), "--q",
                     str(tmp_path / "p.npy")])
    err = capsys.readouterr().err
    assert code == 2 and "--p" in err and "point 1" in err and "not finite" in err, err


@pytest.mark.parametrize("extra, words", [
    (["--size", "20000", "64"], "--size"),
    (["--size", "8", "64"], "--size"),
    (["--vrange", "2", "1"], "--vrange"),
    (["--isolines", "-1"], "--isolines"),
])
def test_render_sizes_and_ranges_are_checked_before_any_work(extra, words, tmp_path, capsys):
    code = cli.main(["render", str(tmp_path / "missing.ngf"), "-o", str(tmp_path / "x.png"), *extra])
    err = capsys.readouterr().err
    assert code == 2 and words in err and not (tmp_path / "x.png").exists(), err


# --- presets -----------------------------------------------------------------------------------------------------

def _flat(cfg) -> dict:
    out = {}
    for k, v in cfg.to_dict().items():
        if isinstance(v, dict) and k != "ratios":
            out.update(v)
        else:
            out[k] = v
    return out


def test_every_preset_is_described_by_settings_it_has():
    from neurogf_warp.training.presets import DESCRIPTIONS, PRESETS, describe, preset

    assert set(DESCRIPTIONS) == set(PRESETS)
    for name, d in DESCRIPTIONS.items():
        have = _flat(preset(name))
        for key, value in d["settings"].items():
            assert key in have, f"{name}: {key} is no setting"
            assert have[key] == value, f"{name} is described with {key}={value} but sets {have[key]}"
            assert f"{key}={value}" in describe(name)
        if "based_on" in d:  # a variant lists exactly what it changes: no claimed change that is a no-op
            base = _flat(preset(d["based_on"]))
            changed = {k for k in have if have[k] != base.get(k)} - {"preset"}
            assert changed == set(d["settings"]), (name, changed)


def test_preset_help_is_the_descriptions():
    from neurogf_warp.training.presets import DESCRIPTIONS, describe

    for name in DESCRIPTIONS:
        assert describe(name) in cli.PRESET_HELP
    assert "longer SDF refinement" not in cli.PRESET_HELP


def test_refine_help_says_what_it_does_without_unsourced_figures(capsys):
    for cmd in ("path", "render", "eval"):
        with pytest.raises(SystemExit):
            cli.main([cmd, "-h"])
        text = " ".join(capsys.readouterr().out.split())
        assert "fast on a GPU" in text and "SDF" in text, cmd
        assert not re.search(r"\d\s*(ms|s) per pair|\d+ ms", text), cmd
