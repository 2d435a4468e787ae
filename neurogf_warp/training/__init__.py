"""Training a NeuroGF for one mesh: settings and presets, data on the device, the trainer and its stages,
CUDA acceleration, checkpoints, the time budget, the step loop, and the one-call ``train()``.

    from neurogf_warp.training import preset, train
    model = train("spot.obj", "spot.ngf", config=preset("cpu"), budget_seconds=180)

Names load on first use, so that ``neurogf_warp.training.run_folder`` (the run folder and the "already trained"
check) works without importing torch.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from neurogf_warp.common.lazy import lazy_exports

# public name -> module of this package that defines it
_EXPORTS = {"train": "api", "RunFiles": "run_folder", "TrainingInterrupted": "loop", "ModelQualityWarning": "quality",
            "PRESETS": "presets", "choose_preset": "presets", "preset": "presets",
            **{name: "config" for name in ("STAGES", "BatchConfig", "DatasetSettings", "NetworkConfig", "RuntimeConfig",
                                           "ScheduleConfig", "TrainConfig")}}

__all__ = ["train", "TrainConfig", "NetworkConfig", "ScheduleConfig", "BatchConfig", "RuntimeConfig",
           "DatasetSettings", "STAGES", "PRESETS", "preset", "choose_preset", "TrainingInterrupted", "RunFiles",
           "ModelQualityWarning"]


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals(), __all__)


if TYPE_CHECKING:
    from neurogf_warp.training.api import train
    from neurogf_warp.training.config import (
        STAGES,
        BatchConfig,
        DatasetSettings,
        NetworkConfig,
        RuntimeConfig,
        ScheduleConfig,
        TrainConfig,
    )
    from neurogf_warp.training.loop import TrainingInterrupted
    from neurogf_warp.training.presets import PRESETS, choose_preset, preset
    from neurogf_warp.training.quality import ModelQualityWarning
    from neurogf_warp.training.run_folder import RunFiles
