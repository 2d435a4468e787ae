"""Training a NeuroGF for one mesh: settings and presets, data on the device, the trainer and its stages,
CUDA acceleration, checkpoints, the time budget, the step loop, and the one-call ``train()``.

    from neurogf_warp.training import preset, train
    model = train("spot.obj", "spot.ngf", config=preset("cpu"), budget_seconds=180)
"""
from neurogf_warp.training.api import train
from neurogf_warp.training.checkpoint import RunFiles
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

__all__ = ["train", "TrainConfig", "NetworkConfig", "ScheduleConfig", "BatchConfig", "RuntimeConfig",
           "DatasetSettings", "STAGES", "PRESETS", "preset", "choose_preset", "TrainingInterrupted", "RunFiles",
           "ModelQualityWarning"]
