"""Atomic checkpoint files: written to a temporary file, fsynced, then renamed over the target.

A run killed mid-write leaves the previous checkpoint intact. Loading uses
`torch.load(..., weights_only=True)` only, so a checkpoint can hold tensors, numbers, strings,
lists and dicts, never pickled code.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable

import torch

from a3cqp_rl.exceptions import CheckpointError

__all__ = ["write_atomic", "save_atomic", "write_text_atomic", "write_output_text", "load_checkpoint"]


def write_atomic(path: str | Path, write: Callable[[BinaryIO], Any]) -> Path:
    """Write `path` with `write(f)` (f: a binary file) atomically: a temp file beside it, fsync, rename; the folder is
    created, the file is readable by other users (mode 0644). A failed write leaves the old file and no temp file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.chmod(tmp, 0o644)  # mkstemp's 0600 would hide the files from other users
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:  # named by the file asked for, not by the temporary one beside it
        Path(tmp).unlink(missing_ok=True)
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def save_atomic(obj: Any, path: str | Path) -> Path:
    """Write `obj` with torch.save to `path` atomically (`write_atomic`); CheckpointError naming the file on OSError."""
    try:
        return write_atomic(path, lambda f: torch.save(obj, f))
    except OSError as exc:  # a full disk, a folder made read-only: name the file, no traceback
        raise CheckpointError(f"cannot write {path}: {exc.strerror or exc}") from None


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically (`write_atomic`)."""
    return write_atomic(path, lambda f: f.write(text.encode("utf-8")))


STDOUT = "-"
"""The output path that means standard output (`--json -`)."""


def write_output_text(path: str | Path, text: str) -> Path | None:
    """Write `text` to standard output where `path` is "-", else to the file `path` atomically; the file's path."""
    if str(path) == STDOUT:
        sys.stdout.write(text if text.endswith("\n") else text + "\n")
        sys.stdout.flush()
        return None
    return write_text_atomic(path, text)


CHECKPOINT_FORMAT = 1
"""The `format` policy.pt and checkpoint.pt files are written with; `load_checkpoint` refuses newer ones."""


def load_checkpoint(path: str | Path, required: tuple[str, ...] = ()) -> dict:
    """Load a checkpoint dict with weights_only=True; clear CheckpointError if missing, corrupt or incomplete."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    if _is_npz(path):  # torch's own error names a .npy "not in a subdirectory"
        raise CheckpointError(f"{path} is a numpy .npz archive, not a policy or checkpoint (an episode of `a3cqp "
                              "evaluate --out`? `a3cqp plot episode` draws those)")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated zip, wrong format, pickled code...
        raise CheckpointError(f"checkpoint {path} is corrupt or not a weights-only torch file "
                              f"(tensors, numbers, strings, lists, dicts): {_reason(exc)}") from None
    if not isinstance(data, dict):
        raise CheckpointError(f"checkpoint {path} holds a {type(data).__name__}, expected a dict")
    missing = [k for k in required if k not in data]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks {missing}; was it written by another program?")
    fmt = data.get("format", CHECKPOINT_FORMAT)
    if not isinstance(fmt, int) or fmt > CHECKPOINT_FORMAT:
        raise CheckpointError(f"checkpoint {path} has format {fmt!r}; this version reads format {CHECKPOINT_FORMAT} "
                              "and older (written by a newer version?)")
    return data


def _is_npz(path: Path) -> bool:
    """Whether `path` is a zip of top-level .npy arrays (numpy's .npz), which torch.load cannot read."""
    import zipfile

    try:
        if not zipfile.is_zipfile(path):
            return False
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except (OSError, zipfile.BadZipFile):
        return False
    return bool(names) and all(n.endswith(".npy") and "/" not in n for n in names)


def _reason(exc: Exception) -> str:
    """torch's load error in one line, without its advice to load with weights_only=False (arbitrary code)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    useful = [ln for ln in lines if "weights_only" not in ln and "Weights only load failed" not in ln
              and not ln.startswith(("(1)", "(2)", "Please", "Check the documentation"))]
    first = (useful or lines or ["no detail"])[0].split(" Please ")[0]
    return f"{type(exc).__name__}: {first}"[:200]
