"""The generalizable commands check their arguments once, before any work: budgets and counts of gen-per-mesh and
gen-train, seeds and sizes of gen-shapes; a refusal is exit code 2 with the argument named, and nothing is
written."""
import os

import pytest
import trimesh

from neurogf_warp.cli import main as cli


def _run(argv, capsys):
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as e:  # argparse's own refusals
        code = e.code
    out = capsys.readouterr()
    return code, out.err


@pytest.fixture
def folder(tmp_path):
    d = tmp_path / "meshes"
    d.mkdir()
    for i in range(2):
        trimesh.creation.icosphere(subdivisions=1).export(d / f"s{i}.obj")
    return d


def test_gen_per_mesh_checks_its_budget_once(folder, tmp_path, capsys):
    code, err = _run(["gen-per-mesh", folder, "-o", tmp_path / "out", "--budget-seconds", "-5"], capsys)
    assert code == 2 and err.count("budget_seconds must be > 0") == 1
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("flag, value, words", [("--sources", "0", "sources must be >= 1"),
                                                ("--targets", "-3", "targets must be >= 1"),
                                                ("--lr", "-1", "lr must be > 0"),
                                                ("--steps", "0", "steps must be >= 1")])
def test_gen_train_checks_its_settings_before_the_ground_truth(folder, tmp_path, capsys, flag, value, words):
    out = tmp_path / "g.pt"
    code, err = _run(["gen-train", folder, "-o", out, flag, value, "--device", "cpu"], capsys)
    assert code == 2 and words in err and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "g.pt.gt").exists()
    code, err = _run(["gen-train", folder, "-o", out, flag, value, "--device", "cpu", "--gt-only"], capsys)
    assert code == 2 and words in err and not (tmp_path / "g.pt.gt").exists()


def test_gen_shapes_refuses_a_negative_seed_and_an_impossible_size(tmp_path, capsys):
    code, err = _run(["gen-shapes", tmp_path / "c", "-n", "2", "--seed", "-1"], capsys)
    assert code == 2 and "--seed" in err and "0 or more" in err
    code, err = _run(["gen-shapes", tmp_path / "c", "-n", str(10 ** 8)], capsys)
    assert code == 2 and "1,000,000" in err
    assert not (tmp_path / "c").exists()


def test_write_collection_refuses_sizes_outside_its_range(tmp_path):
    from neurogf_warp.common.checks import InputError
    from neurogf_warp.generalizable.shapes import write_collection

    for n in (0, 10 ** 7, 2.0, True):
        with pytest.raises(InputError, match="n must be an integer from 1"):
            write_collection(tmp_path / "c", n=n, progress=False)
    assert os.listdir(tmp_path) == []
