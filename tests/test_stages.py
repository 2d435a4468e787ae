"""The stage table: one entry per stage, in run order, training the parts each stage is meant to train."""
import torch

from neurogf_warp.model.network import NeuroGFNet, SdfQuerier
from neurogf_warp.training import STAGES
from neurogf_warp.training.config import RATIOS, ScheduleConfig
from neurogf_warp.training.stages import DRAWS, STAGE_TABLE
from neurogf_warp.training.trainer import Trainer


def _bare_trainer():
    """A Trainer with a small network and querier and nothing else (enough for modes and parameter groups)."""
    torch.manual_seed(0)
    t = object.__new__(Trainer)
    t.net, t.querier = NeuroGFNet(64), SdfQuerier()
    return t


def test_every_stage_has_an_entry_in_run_order():
    assert tuple(STAGE_TABLE) == STAGES
    schedule = ScheduleConfig()
    for name, spec in STAGE_TABLE.items():
        assert spec.name == name and RATIOS[name] == spec.ratio
        assert isinstance(getattr(schedule, spec.lr), float)
        assert spec.draws and set(spec.draws) <= set(DRAWS)
        assert callable(getattr(Trainer, spec.loss))


def test_parameter_groups_and_modes_per_stage():
    t = _bare_trainer()
    net, q = t.net, t.querier
    params = {"querier": list(q.parameters()),
              "joint": list(net.parameters()),
              "refine_dist": list(net.lifting.parameters()) + list(net.gdf_head.parameters()),
              "refine_sdf": list(net.sdf_head.parameters()),
              "refine_path": list(net.cdw_fc.parameters()) + list(net.spf_head.parameters())}
    # the modules each stage runs in train mode (BatchNorm on batch statistics); all others in eval mode
    in_train = {"querier": [q], "joint": [net], "refine_dist": [], "refine_sdf": [net.sdf_head],
                "refine_path": [net.cdw_fc, net.spf_head]}
    assert set(params) == set(STAGES)
    for stage in STAGES:
        got = t.trained_parameters(stage)
        assert [id(p) for p in got] == [id(p) for p in params[stage]], stage
        t.set_modes(stage)
        trained = {id(p) for p in params[stage]}
        for p in [*net.parameters(), *q.parameters()]:
            assert p.requires_grad == (id(p) in trained), stage
        training = {id(m) for top in in_train[stage] for m in top.modules()}
        for m in [*net.modules(), *q.modules()]:
            assert m.training == (id(m) in training), (stage, type(m).__name__)
    assert [s for s in STAGES if STAGE_TABLE[s].weighted] == ["joint", "refine_dist"]
    assert [s for s in STAGES if STAGE_TABLE[s].hard_pairs] == ["joint", "refine_dist"]
    assert [s for s in STAGES if STAGE_TABLE[s].validates] == ["joint", "refine_dist"]


def test_step_caps_and_thread_trials_come_from_the_table():
    from neurogf_warp.training.budget import SLACK, ThreadChooser, fit_budget
    from neurogf_warp.training.config import QUERIER_MAX
    from neurogf_warp.training.presets import preset

    assert ThreadChooser.STAGES_TIMED == ("joint", "refine_dist")
    assert [s for s in STAGES if STAGE_TABLE[s].max_steps is not None] == ["querier"]
    cfg = preset("default")
    per = {"querier": 1e-3, "joint": 3e-3, "refine_dist": 1e-3, "refine_sdf": 3e-4, "refine_path": 1e-3}
    for seconds in (20.0, 3600.0):  # the querier below its cap, then at it
        steps = fit_budget(cfg, per, seconds).stage_steps()
        j = steps["joint"]
        assert steps["querier"] == min(max(1, round(RATIOS["querier"] * j)), QUERIER_MAX)
        used = sum(per[s] * n for s, n in steps.items())
        assert SLACK * seconds * 0.9 <= used <= SLACK * seconds * 1.01, (seconds, steps)  # whole epochs
    assert fit_budget(cfg, per, 3600.0).stage_steps()["querier"] == QUERIER_MAX
