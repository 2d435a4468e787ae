"""Budgets of every odd kind, refused before any work or kept and reported: the generalizable trainer held to the
per-mesh rule, a budget shorter than a run's fixed costs said to be so, and a model file rewritten from a finished
run's checkpoint keeping its verdict."""
import os
import warnings

import numpy as np
import pytest

from neurogf_warp.common.checks import InputError


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -1.0, 0, -0.0, True, "5", 1e12, [5]])
def test_generalizable_budgets_are_checked_before_any_work(tmp_path, bad):
    from neurogf_warp.generalizable.train import GenTrainConfig, train_generalizable

    with pytest.raises(InputError, match="budget_seconds"):
        train_generalizable(tmp_path / "no-such-folder", tmp_path / "g.pt", GenTrainConfig(budget_seconds=bad),
                            device="cpu")
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("bad", [complex(1, 0), np.float32("nan"), np.float64(-3), 2592001, None.__class__])
def test_per_mesh_budgets_of_odd_types_are_refused(tmp_path, bad):
    from neurogf_warp.training import train

    with pytest.raises(InputError, match="budget_seconds"):
        train(tmp_path / "no-such-mesh.obj", tmp_path / "m.ngf", budget_seconds=bad, progress=False)
    assert os.listdir(tmp_path) == []


def test_a_budget_below_the_fixed_costs_is_reported_and_the_verdict_survives_a_rewrite(tmp_path, capsys,
                                                                                       monkeypatch):
    """0.5 s cannot hold the held-out ground truth and a slow save (made 1.5 s slower here, as on a slow disk):
    the run says by how much it went over; deleting the model file and calling again writes it from the
    checkpoint with the same validation figures."""
    import time

    import trimesh

    from neurogf_warp.training import api, train
    from neurogf_warp.training.quality import ModelQualityWarning

    real_save = api.save_model

    def slow_save(*a, **k):
        time.sleep(1.5)
        return real_save(*a, **k)

    monkeypatch.setattr(api, "save_model", slow_save)

    tm = trimesh.creation.icosphere(subdivisions=2)
    mesh = (np.asarray(tm.vertices) * [1.0, 0.8, 0.6], np.asarray(tm.faces))
    out = tmp_path / "m.ngf"
    kw = dict(config="cpu_small", device="cpu", budget_seconds=0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelQualityWarning)
        first = train(mesh, out, progress=True, **kw)
        err = capsys.readouterr().err
        assert "more than its 0.5 s budget" in err and "--budget-seconds" in err
        os.remove(out)
        again = train(mesh, out, progress=True, **kw)
    assert "from the finished run's checkpoint" in capsys.readouterr().err
    for key in ("validation_mre", "validation_mre_upper", "validation_sources", "worse_than_heat", "heat_mre"):
        assert again.config.get(key) == first.config.get(key), key
    assert first.config["validation_mre"] is not None
