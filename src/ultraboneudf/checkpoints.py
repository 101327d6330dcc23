"""Training checkpoints: a killed run resumes where its last checkpoint left it.

A checkpoint holds everything the loop's next step depends on: the network's and the optimiser's
state, the random generator's state, the batch sampler's position, the step, the loss history so
far, the training seconds spent, and (after CAP-UDF's expansion) the new static targets. The data
the loop trains on are not stored: they are made again from the input and the seed. Two keys keep
a checkpoint to its own run: the run's key (:func:`run_key`: the input file's bytes, the resolved
configuration, method, seed and version), checked by :func:`check` before the input is even read,
and the fingerprint of the training data, checked by the loop. Writes are atomic and leave no
temporary file on a signal (a kill while writing leaves the previous checkpoint).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ._version import __version__
from .errors import InputError
from .io import atomic_write_bytes

FORMAT = 1
"""Version of the checkpoint layout; a file of another version is refused."""

_RUN_KEYS: dict[Path, str] = {}
"""The run key each checkpoint path is saved with (set by :class:`Checkpoint`, used by :func:`save`)."""


@dataclass
class Checkpoint:
    """Where and how often a training run saves its state.

    ``path``: the checkpoint file; ``every``: save after every this many steps (0: never save);
    ``resume``: start from ``path`` when it exists (a fresh run otherwise); ``run``: the run's key
    (:func:`run_key`), saved with every checkpoint so that :func:`check` can refuse one of another
    run before any work."""

    path: Path
    every: int = 0
    resume: bool = False
    run: str = ""

    def __post_init__(self) -> None:
        self.path = Path(self.path)
        if self.every < 0:
            raise InputError(f"checkpoint interval must be 0 or more steps, got {self.every}")
        if self.run:
            _RUN_KEYS[self.path.absolute()] = self.run


def run_key(input_sha256: str, config: dict[str, Any], method: str, seed: int, **more: Any) -> str:
    """SHA-256 of what makes a run (the input file's SHA-256, the resolved configuration as a
    dict, the method, the seed, ``more`` such as the sweep options, and this package's version)."""
    blob = json.dumps([input_sha256, config, method, seed, more, __version__], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def fingerprint(*parts: Any) -> str:
    """SHA-256 of the tensors (their bytes) and JSON-able values (dataclasses as dicts) given."""
    import torch

    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, torch.Tensor):
            h.update(part.detach().cpu().contiguous().numpy().tobytes())
        else:
            value = dataclasses.asdict(part) if dataclasses.is_dataclass(part) else part
            h.update(json.dumps(value, sort_keys=True, default=str).encode())
    return h.hexdigest()


def save(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` (tensors moved to the CPU) atomically to ``path``, with the run key of its
    :class:`Checkpoint`."""
    import torch

    buf = io.BytesIO()
    run = _RUN_KEYS.get(Path(path).absolute(), "")
    torch.save({"format": FORMAT, "written_by": "ultraboneudf", "run": run, **state}, buf)
    atomic_write_bytes(path, buf.getvalue())


def _read(path: Path) -> dict[str, Any]:
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a truncated or foreign file: one line, not a traceback
        raise InputError(f"{path}: not a readable training checkpoint ({type(exc).__name__}); "
                         f"delete it or run without --resume") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise InputError(f"{path}: not a checkpoint of this version; delete it or run without --resume")
    return state


def check(checkpoint: Checkpoint, overwrite: bool = False) -> None:
    """Before any work: :class:`InputError` naming ``checkpoint.path`` when the file there cannot
    be used. It must not be a folder or a special file; with ``resume``, an existing file must be
    a checkpoint of this very run (the same :func:`run_key`); without, one that is not a checkpoint
    of this package is not replaced unless ``overwrite``."""
    path = checkpoint.path
    if not os.path.lexists(path):
        return
    if path.is_dir() or not path.is_file():
        raise InputError(f"{path}: is {'a folder' if path.is_dir() else 'not a regular file'}; the "
                         f"training checkpoint needs that name (move it, or choose another output name)")
    if checkpoint.resume:
        state = _read(path)
        if checkpoint.run and state.get("run") != checkpoint.run:
            raise InputError(f"{path}: this checkpoint was made by another run (a different input, "
                             f"configuration, method, seed or version); delete it or run without --resume")
        return
    if overwrite:
        return
    try:
        _read(path)
    except InputError:
        raise InputError(f"{path}: exists and is not a training checkpoint of ultraboneudf; --checkpoint-every "
                         f"would replace it (move it, or --overwrite)") from None


def load(path: Path, expected_fingerprint: str) -> dict[str, Any]:
    """The state saved at ``path``; :class:`InputError` when it is unreadable, of another format,
    or was made by another run (input, configuration or seed)."""
    state = _read(path)
    if state.get("fingerprint") != expected_fingerprint:
        raise InputError(f"{path}: this checkpoint was made by another run (a different input, "
                         f"configuration or seed); delete it or run without --resume")
    return state
