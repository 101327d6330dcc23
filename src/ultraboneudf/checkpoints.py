"""Training checkpoints: a killed run resumes where its last checkpoint left it.

A checkpoint holds everything the loop's next step depends on: the network's and the optimiser's
state, the random generator's state, the batch sampler's position, the step, the loss history so
far, the training seconds spent, and (after CAP-UDF's expansion) the new static targets. The data
the loop trains on are not stored: they are made again from the input and the seed, and a
fingerprint of them, of the configuration and of the seed must match, so a checkpoint never
resumes a different run. Writes are atomic (a kill while writing leaves the previous checkpoint).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .errors import InputError
from .io import atomic_write_bytes

FORMAT = 1
"""Version of the checkpoint layout; a file of another version is refused."""


@dataclass
class Checkpoint:
    """Where and how often a training run saves its state.

    ``path``: the checkpoint file; ``every``: save after every this many steps (0: never save);
    ``resume``: start from ``path`` when it exists (a fresh run otherwise)."""

    path: Path
    every: int = 0
    resume: bool = False

    def __post_init__(self) -> None:
        self.path = Path(self.path)
        if self.every < 0:
            raise InputError(f"checkpoint interval must be 0 or more steps, got {self.every}")


def fingerprint(*parts: Any) -> str:
    """SHA-256 of the tensors (their bytes) and JSON-able values (dataclasses as dicts) given."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, torch.Tensor):
            h.update(part.detach().cpu().contiguous().numpy().tobytes())
        else:
            value = dataclasses.asdict(part) if dataclasses.is_dataclass(part) else part
            h.update(json.dumps(value, sort_keys=True, default=str).encode())
    return h.hexdigest()


def save(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` (tensors moved to the CPU) atomically to ``path``."""
    buf = io.BytesIO()
    torch.save({"format": FORMAT, **state}, buf)
    atomic_write_bytes(path, buf.getvalue())


def load(path: Path, expected_fingerprint: str) -> dict[str, Any]:
    """The state saved at ``path``; :class:`InputError` when it is unreadable, of another format,
    or was made by another run (input, configuration or seed)."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a truncated or foreign file: one line, not a traceback
        raise InputError(f"{path}: not a readable training checkpoint ({type(exc).__name__}); "
                         f"delete it or run without --resume") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise InputError(f"{path}: not a checkpoint of this version; delete it or run without --resume")
    if state.get("fingerprint") != expected_fingerprint:
        raise InputError(f"{path}: this checkpoint was made by another run (a different input, "
                         f"configuration or seed); delete it or run without --resume")
    return state
