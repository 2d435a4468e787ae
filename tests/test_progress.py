"""Progress output: a bar on a terminal; plain, periodic lines in a file, a pipe or a CI log; a steady total."""
import io
import subprocess
import sys

from neurogf_warp.common.progress import Progress


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_plain_lines_off_a_terminal_are_periodic_and_bounded(tmp_path):
    clock = FakeClock()
    with open(tmp_path / "log.txt", "w") as f:
        bar = Progress(4000, "training", unit="step", stream=f, every_s=20.0, clock=clock)
        for _ in range(4000):  # 0.05 s per step: 200 s of work
            clock.t += 0.05
            bar.update(1)
        bar.set_postfix("joint loss 0.1")
        bar.close()
    text = (tmp_path / "log.txt").read_text()
    lines = text.splitlines()
    assert "\r" not in text
    assert 9 <= len(lines) <= 11, lines  # one per 20 s of 200 s, and the last
    assert lines[-1] == "training: 4,000/4,000 steps (100%), 20 steps/s, 200 s elapsed, joint loss 0.1"
    assert lines[0].startswith("training: 400/4,000 steps (10%)")


def test_short_work_off_a_terminal_is_one_line():
    out = io.StringIO()  # not a terminal
    with Progress(8, "ground truth", unit="source", stream=out) as bar:
        for _ in range(8):
            bar.update(1)
    assert out.getvalue().count("\n") == 1 and out.getvalue().startswith("ground truth: 8/8 sources (100%)")


def test_a_terminal_gets_the_bar():
    out = Terminal()
    with Progress(50, "paths", unit="path", stream=out) as bar:
        for _ in range(50):
            bar.update(1)
    assert "\r" in out.getvalue() and "50/50" in out.getvalue()


def test_off_shows_nothing():
    out = io.StringIO()
    with Progress(5, "x", on=False, stream=out) as bar:
        bar.update(5)
    assert out.getvalue() == ""


def test_a_replanned_total_changes_only_when_it_moves_by_a_tenth():
    """A budget re-plans every 2 s: 90 re-plans whose totals drift from 4,000 to 3,000 with +-3% noise."""
    import numpy as np

    rng = np.random.default_rng(0)
    bar = Progress(4000, "training", stream=io.StringIO(), total_tolerance=0.1)
    plans = np.linspace(4000, 3000, 90) * (1 + rng.uniform(-0.03, 0.03, 90))
    changed = sum(bar.set_total(int(p)) for p in plans)
    assert changed == bar.total_changes and 1 <= changed <= 4, changed
    assert abs(bar.total - 3000) <= 0.1 * 3000 + 100
    bar.n = 3017
    bar.finish()  # the count done is the total after all
    assert bar.total == 3017


def test_an_exact_total_is_taken_as_it_is():
    bar = Progress(100, "ground truth", stream=io.StringIO())
    assert bar.set_total(99) and bar.total == 99


def test_a_closed_stderr_shows_nothing_and_does_not_fail(monkeypatch):
    monkeypatch.setattr(sys, "stderr", None)
    with Progress(3, "x") as bar:
        bar.update(3)


CHILD = """
from neurogf_warp.common.progress import Progress
with Progress(200000, "work", unit="item") as bar:
    for _ in range(200000):
        bar.update(1)
"""


def test_stderr_into_a_pipe_gets_no_carriage_returns():
    res = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "\r" not in res.stderr and res.stdout == ""
    lines = res.stderr.splitlines()
    assert 1 <= len(lines) <= 3 and lines[-1].startswith("work: 200,000/200,000 items (100%)"), lines


def test_dataset_and_training_progress_into_a_file_are_plain_lines(ellipsoid, tiny_dataset, tmp_path, capsys):
    """The training loop and the dataset builder use the progress module: with stderr captured (not a terminal) they write
    a few plain lines and no carriage return."""
    import warnings

    import torch

    from neurogf_warp.dataset.build import build_dataset
    from neurogf_warp.training import preset, train
    from neurogf_warp.training.quality import ModelQualityWarning

    build_dataset(ellipsoid, None, preset("cpu_small").data, device="cpu", progress=True)
    err = capsys.readouterr().err
    assert "\r" not in err and "ground truth: " in err
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ModelQualityWarning)  # 20 steps make no model to speak of
            cfg = preset("cpu_small", querier_steps=5, epochs=1, iters_per_epoch=20)
            model = train(ellipsoid, tmp_path / "m.ngf", config=cfg, dataset=tiny_dataset, device="cpu",
                          progress=True)
    finally:
        torch.set_num_threads(n)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("training: ")]
    assert "\r" not in err and 1 <= len(lines) <= 10, err
    done, total = lines[-1].split()[1].split("/")
    assert done == total, lines[-1]  # the last line: every step done, of a total that is the steps done
    steps = model.config["steps"]
    assert int(done.replace(",", "")) == sum(steps.values())
    saved = next(ln for ln in err.splitlines() if ln.startswith("saved "))
    assert f"{steps['joint']:,} joint steps, {sum(steps.values()):,} in all" in saved, saved  # the steps that ran
