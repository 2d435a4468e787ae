"""What a short-budget training run says about its steps: no count it cannot keep before the steps, the count it
made after them."""
import re
import warnings

import pytest

from neurogf_warp.training.budget import short_budget_done, short_budget_said


def test_the_message_before_the_steps_promises_no_count():
    line = short_budget_said(1 / 16)
    assert "batches x0.0625" in line and "follows the measured speed" in line
    assert not re.search(r"\d[\d,]* joint steps", line)


def test_the_message_after_the_steps_says_what_ran():
    line = short_budget_done({"scale": 1 / 16, "planned_joint_steps": 2000}, 58)
    assert line.startswith("short budget: 58 joint steps ran at batches x0.0625")
    assert "2,000 planned" in line and "34.5x" in line
    assert "planned" not in short_budget_done({"scale": 0.25, "planned_joint_steps": 110}, 100)  # close to plan
    assert "the budget ended first" in short_budget_done({"scale": 0.5, "planned_joint_steps": 10}, 0)


@pytest.mark.slow
def test_a_short_cpu_run_says_the_steps_it_made(tmp_path, ellipsoid, capsys):
    from neurogf_warp.training import train
    from neurogf_warp.training.quality import ModelQualityWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelQualityWarning)
        model = train(ellipsoid, tmp_path / "m.ngf", device="cpu", budget_seconds=8, progress=True)
    err = capsys.readouterr().err
    made = model.config["steps"]["joint"]
    before = [ln for ln in err.splitlines() if "short budget: batches" in ln]
    after = [ln for ln in err.splitlines() if re.search(r"short budget: [\d,]+ joint steps ran", ln)]
    assert len(before) == 1 and not re.search(r"\d[\d,]* joint steps", before[0]), before
    assert len(after) == 1 and after[0].startswith(f"short budget: {made:,} joint steps ran"), (after, made)
