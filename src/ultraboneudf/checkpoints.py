"""Training checkpoints: a killed run resumes where its last checkpoint left it.

A checkpoint holds everything the loop's next step depends on: the network's and the optimiser's
state, the random generator's state, the batch sampler's position, the step, the loss history so
far, the training seconds spent, and (after CAP-UDF's expansion) the new static targets. The data
the loop trains on are not stored: they are made again from the input and the seed.

The file is one line of JSON after the line :data:`MAGIC` (the format, the step, the run's key:
:func:`run_key`, of the input file's bytes, the configuration, method, seed and version; and the
length and SHA-256 of what follows), then the state as ``torch.save`` writes it. The header is read without PyTorch, so :func:`check` refuses a
file that is not a checkpoint, or one of another run, before any work; the loop also checks the
fingerprint of its training data. Writes are atomic and leave no temporary file on a signal (a
kill while writing leaves the previous checkpoint).
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

FORMAT = 2
"""Version of the checkpoint layout; a file of another version is refused."""
MAGIC = b"ultraboneudf checkpoint\n"
_HEADER_MAX = 4096

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
    """SHA-256 of what makes a run (the input file's SHA-256, the configuration as a dict, the
    method, the seed, ``more`` such as the preset and the sweep options, and this package's version)."""
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
    """Write ``state`` (tensors moved to the CPU) atomically to ``path``, after a header with the
    run key of its :class:`Checkpoint`."""
    import torch

    buf = io.BytesIO()
    torch.save(state, buf)
    payload = buf.getvalue()
    header = {"format": FORMAT, "run": _RUN_KEYS.get(Path(path).absolute(), ""), "step": state.get("step"),
              "bytes": len(payload), "sha256": hashlib.sha256(payload).hexdigest()}
    atomic_write_bytes(path, MAGIC + json.dumps(header).encode() + b"\n" + payload)


def read_header(path: Path) -> dict[str, Any] | None:
    """The header of the checkpoint at ``path`` (no PyTorch needed), or ``None`` when the file is
    not a checkpoint of this package."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(MAGIC) + _HEADER_MAX)
    except OSError:
        return None
    if not head.startswith(MAGIC) or b"\n" not in head[len(MAGIC):]:
        return None
    try:
        header = json.loads(head[len(MAGIC):head.index(b"\n", len(MAGIC))])
    except ValueError:
        return None
    return header if isinstance(header, dict) and "format" in header else None


def read(path: Path) -> dict[str, Any]:
    """The state saved at ``path``; :class:`InputError` when the file is not a readable checkpoint
    of this version."""
    import torch

    payload = _payload(path)
    try:
        return torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as exc:  # a truncated file: one line, not a traceback
        raise InputError(f"{path}: not a readable training checkpoint ({type(exc).__name__}); "
                         f"delete it or run without --resume") from None


def _payload(path: Path) -> bytes:
    """The state's bytes after the header, checked against the header's length and SHA-256."""
    header = read_header(path)
    if header is None:
        raise InputError(f"{path}: not a training checkpoint of ultraboneudf; delete it or run without --resume")
    if header["format"] != FORMAT:
        raise InputError(f"{path}: not a checkpoint of this version; delete it or run without --resume")
    data = Path(path).read_bytes()
    payload = data[data.index(b"\n", len(MAGIC)) + 1:]
    if len(payload) != header.get("bytes") or hashlib.sha256(payload).hexdigest() != header.get("sha256"):
        raise InputError(f"{path}: a checkpoint cut short or damaged ({len(payload):,} of {header.get('bytes', 0):,} "
                         f"bytes); delete it or run without --resume")
    return payload


def check(checkpoint: Checkpoint, overwrite: bool = False) -> None:
    """Before any work (no PyTorch needed): :class:`InputError` naming ``checkpoint.path`` when the
    file there cannot be used. It must not be a folder or a special file; with ``resume``, an
    existing file must be a checkpoint of this version made by this very run (the same
    :func:`run_key`); without, a file that is not a checkpoint of this package is not replaced
    unless ``overwrite``."""
    path = checkpoint.path
    if not os.path.lexists(path):
        return
    if path.is_dir() or not path.is_file():
        raise InputError(f"{path}: is {'a folder' if path.is_dir() else 'not a regular file'}; the "
                         f"training checkpoint needs that name (move it, or choose another output name)")
    header = read_header(path)
    if checkpoint.resume:
        _payload(path)
        if checkpoint.run and header.get("run") != checkpoint.run:
            raise InputError(f"{path}: this checkpoint was made by another run (a different input, preset, "
                             f"configuration, method, seed or version); delete it or run without --resume")
        return
    if header is None and not overwrite:
        raise InputError(f"{path}: exists and is not a training checkpoint of ultraboneudf; "
                         f"--checkpoint-every would replace it (move it, or --overwrite)")


def load(path: Path, expected_fingerprint: str) -> dict[str, Any]:
    """The state saved at ``path``; :class:`InputError` when it is unreadable, of another format,
    or was made by another run (input, configuration or seed)."""
    state = read(path)
    if state.get("fingerprint") != expected_fingerprint:
        raise InputError(f"{path}: this checkpoint was made by another run (a different input, "
                         f"configuration or seed); delete it or run without --resume")
    return state
