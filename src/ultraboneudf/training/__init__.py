"""Training a field: the one optimisation loop (one scan or K at once), its batch draws and
schedule, its bookkeeping, and the loss terms."""

from .log import LoopLog
from .loop import (Expansion, StepDraw, TrainingData, TrainResult, cpu_threads, flush_denormals, loss_terms,
                   make_optimizer, train, train_many)
from .samplers import SAMPLERS, EpochSampler, StridedSampler, learning_rate
from .scans import OneScan, StackedMLP

__all__ = ["SAMPLERS", "EpochSampler", "Expansion", "LoopLog", "OneScan", "StackedMLP", "StepDraw", "StridedSampler",
           "TrainResult", "TrainingData", "cpu_threads", "flush_denormals", "learning_rate", "loss_terms", "make_optimizer",
           "train", "train_many"]
