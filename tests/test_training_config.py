"""Training settings: names, text conversion and range checks, presets, (de)serialization. No training here."""
import json

import pytest

from neurogf_warp.model.network import NeuroGFNet
from neurogf_warp.training import PRESETS, TrainConfig, choose_preset, preset
from neurogf_warp.training.config import LEAVES, parse_assignments


def test_set_reaches_every_setting_by_flat_or_dotted_name_and_converts_text():
    cfg = TrainConfig()
    for name, (group, typ) in LEAVES.items():  # every leaf can be set from text through its flat name
        old = getattr(cfg if group is None else getattr(cfg, group), name)
        text = json.dumps(old) if isinstance(old, dict) else "none" if old is None else str(old).lower()
        new = cfg.set(**{name: text})
        assert getattr(new if group is None else getattr(new, group), name) == old, name
    c = cfg.set(**{"schedule.lr": "3e-3", "batch_g": "4096", "amp": "false", "ratios": '{"refine_dist": 2}',
                   "querier_steps": "none", "D": 128, "n_sources": "256", "seed": "7"})
    assert c.schedule.lr == 0.003 and c.batches.batch_g == 4096 and c.runtime.amp is False
    assert c.schedule.ratios == {"refine_dist": 2} and c.schedule.querier_steps is None
    assert c.network.D == 128 and c.data.n_sources == 256 and c.seed == 7
    assert cfg.schedule.lr == 0.01  # set() returns a copy


@pytest.mark.parametrize("key,value,match", [
    ("lr", "abc", "lr must be a number"), ("batch_g", "1.5", "batch_g must be an integer"),
    ("amp", "maybe", "amp must be true or false"), ("ratios", "[1]", "ratios must be a mapping"),
    ("ratios", '{"warmup": 1}', "ratios must map stage names"), ("D", "100", "D must be one of"),
    ("lr", "-1", "lr must be > 0"), ("dist_loss", "huber", "dist_loss must be one of"),
    ("loss_weights", '{"foo": 1}', "loss_weights: unknown terms"), ("batch_g", "0", "batch_g must be >= 1"),
    ("path_window", "true", None), ("target_pool", "everything", "target_pool must be"),
    ("n_sources", "0", "n_sources must be >= 1"), ("epochs", "none", "epochs must be an integer"),
    ("schedul.lr", "1", "unknown setting"), ("lrr", "1", "did you mean lr"),
])
def test_bad_values_are_refused_with_the_setting_named(key, value, match):
    if match is None:  # path_window is already on by default; with path_residual off it must fail
        with pytest.raises(ValueError, match="needs path_residual"):
            TrainConfig().set(path_residual="false", **{key: value})
        return
    with pytest.raises(ValueError, match=match):
        TrainConfig().set(**{key: value})


def test_parse_assignments():
    assert parse_assignments(["batch_g=128", "amp=true", "schedule.lr=3e-3"]) == \
        {"batch_g": "128", "amp": "true", "schedule.lr": "3e-3"}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_assignments(["lr"])
    with pytest.raises(ValueError, match="unknown setting 'nonsense'"):
        parse_assignments(["nonsense=1"])


def test_round_trips_and_the_flat_format_of_older_checkpoints():
    cfg = preset("cpu", lr=3e-3, ratios={"refine_dist": 2.0})
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    flat = {"D": 64, "fourier": 2, "epochs": 3, "lr": 0.01, "ratios": {}, "dataset_options": {"n_sources": 64,
                                                                                              "seed": 0}}
    old = TrainConfig.from_dict(flat)
    assert old.network.D == 64 and old.schedule.epochs == 3 and old.data.n_sources == 64
    with pytest.raises(ValueError, match="unknown batches settings"):
        TrainConfig.from_dict({"batches": {"batch_x": 1}})
    # settings removed since: their "off" value loads, anything else is refused
    assert TrainConfig.from_dict(dict(flat, refine_amp=True, refine_batch_paths=None)) == old
    with pytest.raises(ValueError, match="refine_batch_paths=8192 was removed"):
        TrainConfig.from_dict(dict(flat, refine_batch_paths=8192))


def test_presets():
    assert set(PRESETS) >= {"default", "paper", "cpu", "cpu_small"}
    # the GPU recipe: the hard-pair pool, 4 refine_dist steps per joint step and the plain AdamW on top of the
    # dataclass defaults; the CPU presets keep uniform batches (not measured there) and torch's AdamW
    assert preset("default") == TrainConfig(preset="default").set(hard_share=0.25, optimizer="plain",
                                                                    ratios={"refine_dist": 4.0, "refine_sdf": 0.4})
    assert preset("cpu").schedule.hard_share == 0 and preset("paper").schedule.hard_share == 0
    assert preset("cpu").runtime.optimizer == "torch" and preset("landmarks").runtime.optimizer == "plain"
    assert preset("landmarks").network.landmarks == preset("cpu_landmarks").network.landmarks == 256
    cpu = preset("cpu")
    assert cpu.preset == "cpu" and cpu.network.D < 256 and cpu.batches.batch_g < TrainConfig().batches.batch_g
    assert choose_preset("cpu", 3000) == "cpu" and choose_preset("cuda:0", 3000) == "default"
    with pytest.raises(ValueError, match="unknown preset 'gpu'; known: default"):
        preset("gpu")


def test_paper_preset_gives_the_official_network_and_recipe():
    cfg = preset("paper")
    net = cfg.network.build()
    assert net.options == {"fourier": 0, "euclid": False, "path_residual": False, "path_width": 1,
                           "path_window": False}
    assert net.lifting[0].linear.weight.shape == (64, 3)  # the released layout
    assert cfg.schedule.dist_loss == "l1" and cfg.stage_steps()["refine_dist"] == 0
    assert cfg.ratio("refine_path") == 0.1 and cfg.schedule.refine_path_lr == 1e-3
    defaults = NeuroGFNet(64, TrainConfig().network.fourier).lifting[0].linear.weight.shape
    assert defaults == (16, 3 + 6 * TrainConfig().network.fourier)


def test_short_budget_batches_shrink_to_the_devices_floor():
    from neurogf_warp.training.budget import SHORT_BUDGET_STEPS, short_budget_scale
    from neurogf_warp.training.config import BatchConfig

    n = SHORT_BUDGET_STEPS
    assert [short_budget_scale(k) for k in (1, n // 4, n // 2 - 1, n // 2, n - 1, n, 10 * n)] == \
        [0.25, 0.25, 0.25, 0.5, 0.5, 1.0, 1.0]
    assert [short_budget_scale(k, "cpu") for k in (1, n // 8 - 1, n // 8, n // 4 - 1, n // 4, n)] == \
        [1 / 16, 1 / 16, 1 / 8, 1 / 8, 1 / 4, 1.0]
    s = BatchConfig().scaled(1 / 16, sdf_factor=0.25)
    assert (s.batch_g, s.batch_paths_g, s.batch_sdf, s.batch_querier) == (4096, 128, 7500, 22500)
    b = BatchConfig()
    q = b.scaled(0.25)
    assert (q.batch_g, q.batch_l1, q.batch_l2, q.batch_sdf, q.batch_querier) == \
        (b.batch_g // 4, b.batch_l1 // 4, b.batch_l2 // 4, b.batch_sdf // 4, b.batch_querier // 4)
    assert (q.batch_paths_g, q.batch_paths_l, q.batch_surf) == (512, 512, 64)
    assert q.sdf_pool == b.sdf_pool and q.short_budget_batches
    tiny = BatchConfig(batch_paths_g=2, batch_surf=2).scaled(0.25)
    assert tiny.batch_paths_g == 1 and tiny.batch_surf <= tiny.batch_paths_g and tiny.validate() is None
    from neurogf_warp.training import preset

    assert preset("default", short_budget_batches="false").batches.short_budget_batches is False
