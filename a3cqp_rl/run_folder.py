"""Run folders that cannot be lost or mixed: one writer at a time, no silent overwrite, no silent relabelling.

Rules (`RunFolder.open`):
  * a folder that holds a run (checkpoint.pt or policy.pt) is not started again unless `force` (its run files are
    then removed first) or `resume`;
  * an exclusive lock (OUT/.lock, flock) so two processes cannot write one folder; it dies with its process;
  * temporary files a killed writer left (`.NAME.*.tmp` of `checkpoint.save_atomic`) are removed;
  * `config_changes` lists what a resume would change against the run's recorded config; the trainer refuses
    them unless overridden, and then appends them to OUT/overrides.log.
"""

from __future__ import annotations

import datetime
import errno
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path

from a3cqp_rl.exceptions import A3CQPError, CheckpointError

__all__ = ["RunFolder", "RunFolderError", "RUN_FILES", "check_output_path", "config_changes", "policy_file",
           "remove_outputs"]

RUN_FILES = ("checkpoint.pt", "policy.pt", "metrics.csv", "config.yaml", "overrides.log")
"""What a run writes, besides the tb/ folder and its plots; `force` removes these."""
RUN_PLOTS = ("policy_map.png", "policy_map.pdf", "loss_curves.png", "regions.png", "transfer.png", "evaluation.json")
"""What `a3cqp train` writes after training; `force` removes these too (left, they would describe the old run)."""


def remove_outputs(path: Path) -> None:
    """Remove what `a3cqp train` writes after training (RUN_PLOTS) from `path`: a run's folder or a sweep's."""
    for name in RUN_PLOTS:
        (path / name).unlink(missing_ok=True)


class RunFolderError(A3CQPError):
    """A run folder cannot be used as asked (holds a run, is locked, is not a folder, cannot be written)."""


def check_output_path(path: str | Path, flag: str, *, folder: bool = False) -> Path:
    """`path` as given, checked before any work that ends by writing it: a file (`folder` False) or a folder that
    can be created or written there; RunFolderError naming the command-line `flag` otherwise."""
    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise RunFolderError(f"{flag} {path} is a file, expected a folder")
    if not folder and path.is_dir():
        raise RunFolderError(f"{flag} {path} is a folder, expected a file name")
    existing = path if folder else path.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise RunFolderError(f"{flag} {path}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise RunFolderError(f"{flag} {path}: cannot write into {existing}")
    try:  # os.access says yes to root everywhere, also on a read-only or virtual file system (/proc): try it
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".a3cqp-write-check-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise RunFolderError(f"{flag} {path}: cannot write into {existing} ({exc.strerror or exc})") from None
    return path


def policy_file(path: str | Path) -> Path:
    """The policy file a `--policy` argument names: the file itself, or a run folder's policy.pt; a folder with only
    checkpoint.pt is a CheckpointError that says which file to pass."""
    path = Path(path)
    if not path.is_dir():
        return path
    seeds = sorted(p.name for p in path.glob("seed_*") if (p / "policy.pt").is_file())
    if not (path / "policy.pt").is_file() and seeds:
        raise CheckpointError(f"{path} is a sweep of {len(seeds)} run(s) ({', '.join(seeds[:4])}"
                              f"{', ...' if len(seeds) > 4 else ''}): pass its seed folders, e.g. {path}/seed_*")
    if not (path / "policy.pt").is_file() and (path / "checkpoint.pt").is_file():
        raise CheckpointError(f"{path} holds no policy.pt (a run writes it when it ends or is stopped), only "
                              f"checkpoint.pt: pass {path / 'checkpoint.pt'} for its last parameters, or finish the "
                              f"run with a3cqp train --out {path} --resume")
    return path / "policy.pt"


class RunFolder:
    """An output folder held by this process (lock taken); `close()` (or the process ending) releases it."""

    def __init__(self, path: Path, lock_fd: int, created: bool = False) -> None:
        """Use `RunFolder.open`."""
        self.path, self._fd, self.created = path, lock_fd, created

    @classmethod
    def open(cls, path: str | Path, *, resume: bool = False, force: bool = False) -> RunFolder:
        """Create/lock `path` for a new run (refused if it holds one, unless `force`) or for a resume."""
        path = Path(path)
        if path.exists() and not path.is_dir():
            raise RunFolderError(f"--out {path} is a file, expected a folder for the run's files")
        created = not path.exists()
        try:
            path.mkdir(parents=True, exist_ok=True)
            fd = os.open(path / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise RunFolderError(f"cannot write to {path}: {exc.strerror or exc}") from None
        folder = cls(path, fd, created)
        try:
            folder._lock()
            if not resume and folder.holds_run():
                if not force:
                    resumable = (path / "checkpoint.pt").is_file()
                    raise RunFolderError(
                        f"{path} already holds a run ({', '.join(folder.existing())}); "
                        + ("continue it with --resume, " if resumable else "without checkpoint.pt it cannot be "
                           "resumed: ")
                        + "start over with --force (deletes it), or choose another --out")
                folder.clear()
            folder.remove_temporary_files()
        except BaseException:
            folder.close()
            raise
        return folder

    def _lock(self) -> None:
        import fcntl

        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EACCES):
                raise RunFolderError(f"cannot lock {self.path / '.lock'}: {exc.strerror}") from None
            other = os.pread(self._fd, 64, 0).decode(errors="replace").strip() or "?"
            raise RunFolderError(f"{self.path} is being written by another process (pid {other}); wait for it or "
                                 "choose another --out") from None
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, str(os.getpid()).encode(), 0)

    def holds_run(self) -> bool:
        """Whether a run was started here (a checkpoint or a final policy exists)."""
        return any((self.path / f).exists() for f in ("checkpoint.pt", "policy.pt"))

    def existing(self) -> list[str]:
        """Names of the run files present."""
        return [f for f in RUN_FILES if (self.path / f).exists()]

    def clear(self) -> None:
        """Remove the previous run's files (RUN_FILES, plots, tb/); nothing else in the folder."""
        import shutil

        for name in RUN_FILES:
            (self.path / name).unlink(missing_ok=True)
        remove_outputs(self.path)
        shutil.rmtree(self.path / "tb", ignore_errors=True)

    def remove_temporary_files(self) -> list[Path]:
        """Delete `.NAME.*.tmp` files that a killed writer left (we hold the lock: nobody is writing them)."""
        removed = []
        for name in (*RUN_FILES, "policy.pt"):
            for tmp in self.path.glob(f".{name}.*.tmp"):
                tmp.unlink(missing_ok=True)
                removed.append(tmp)
        return removed

    def record_overrides(self, update: int, changes: Iterable[str]) -> Path:
        """Append the config changes a resume at `update` was allowed to make to OUT/overrides.log."""
        log = self.path / "overrides.log"
        stamp = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
        with log.open("a") as f:
            for c in changes:
                f.write(f"{stamp} resume at update {update}: {c}\n")
        return log

    def close(self, *, failed: bool = False) -> None:
        """Release the lock (idempotent). `failed`: the work stopped early; a folder this open created that holds
        nothing but its lock is removed, so a run that never started leaves no empty folder behind."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
            if failed and self.created and [p.name for p in self.path.iterdir()] == [".lock"]:
                (self.path / ".lock").unlink(missing_ok=True)
                try:
                    self.path.rmdir()
                except OSError:  # another process wrote into it meanwhile: keep it
                    pass

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def config_changes(old: dict, new: dict, ignore: Iterable[str] = (), prefix: str = "") -> list[str]:
    """'key: old -> new' for each dotted key whose value differs between two config dicts (keys in `ignore` skipped)."""
    ignore = set(ignore)
    out = []
    for key in sorted(set(old) | set(new)):
        dotted = f"{prefix}{key}"
        if dotted in ignore:
            continue
        a, b = old.get(key, "<unset>"), new.get(key, "<unset>")
        if isinstance(a, dict) and isinstance(b, dict):
            out += config_changes(a, b, ignore, f"{dotted}.")
        elif a != b:
            out.append(f"{dotted}: {a!r} -> {b!r}")
    return out
