"""Training metrics to OUT/metrics.csv (one row per `a2c.log_every` updates) and, if installed, TensorBoard (OUT/tb).

A resumed run first drops the rows a killed run wrote after its checkpoint (and a partial final row), so every step
is logged once; TensorBoard hides those events with `purge_step`.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from a3cqp_rl.checkpoint import write_text_atomic
from a3cqp_rl.regions import REGION_COLUMNS
from a3cqp_rl.run_folder import RunFolderError

__all__ = ["METRICS", "TRANSFER_COLUMNS", "CSV_COLUMNS", "RunLog", "truncate_csv"]

METRICS = ("policy_loss", "value_loss", "entropy", "grad_norm", "explained_variance")
TRANSFER_COLUMNS = ("transfer_margin", "free_w1", "free_w2", "guided_w2", "guided_fd")
"""metrics.csv columns of a per-axis policy's live parameters (a3cqp_rl.transfer): mean ẇ1 and ẇ2 in the Panda's free
motion, mean ẇ2 and ḟd under the operator's push, and the margin min(free ẇ1, −free ẇ2, guided ẇ2, −guided ḟd); NaN
for other policies."""
CSV_COLUMNS = ("step", "update", *METRICS, "episode_reward", "episodes", "steps_per_second", *REGION_COLUMNS,
               *TRANSFER_COLUMNS)
"""metrics.csv columns. The region columns check the policy policy.pt would hold at that row (with `a2c.average_last`,
the running average once it has begun); NaN on rows without a Fig. 5 check (point mass only, `a2c.region_checks`)."""


class RunLog:
    """Appends metric rows to OUT/metrics.csv and OUT/tb; `out` None logs nowhere (rows are still returned)."""

    def __init__(self, out: Path | None, start_update: int, per_update: int, log_every: int,
                 finished: bool = False) -> None:
        """Open the log of a run that starts (or resumes) after update `start_update` (`finished`: the run ended
        there, and its final row stays)."""
        self.path = out / "metrics.csv" if out is not None else None
        self.tb = None
        self._tb_args = (out, start_update * per_update + 1)  # the writer is made on the first row: start-up stays short
        if out is not None:
            truncate_csv(self.path, keep_until_update=start_update, log_every=log_every, keep_last=finished)

    def write(self, row: dict[str, float]) -> None:
        """Append `row` (CSV_COLUMNS) to metrics.csv and its finite values to TensorBoard under a2c/."""
        if self.path is None:
            return
        new = not self.path.exists()
        try:
            with self.path.open("a", newline="") as f:
                w = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
                if new:
                    w.writeheader()
                w.writerow(row)
        except OSError as exc:
            raise RunFolderError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        if self._tb_args is not None:
            self.tb, self._tb_args = _tensorboard(*self._tb_args), None
        if self.tb is not None:
            for k, v in row.items():
                if k not in ("step", "update") and math.isfinite(v):
                    self.tb.add_scalar(f"a2c/{k}", v, row["step"])

    def close(self) -> None:
        """Flush and close TensorBoard."""
        if self.tb is not None:
            self.tb.close()


def truncate_csv(path: Path, keep_until_update: int, log_every: int, keep_last: bool = False) -> None:
    """Drop metric rows past the checkpoint we resume from (and its partial final row, which the run logs again
    whole as it goes on): no step logged twice. `keep_last`: the run ended at that checkpoint and goes on no
    further, so its final row stays."""
    if not path.exists():
        return
    try:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        keep = [r for r in rows if int(r["update"]) <= keep_until_update
                and (int(r["update"]) % log_every == 0 or (keep_last and int(r["update"]) == keep_until_update))]
    except (OSError, UnicodeDecodeError, csv.Error, KeyError, TypeError, ValueError) as exc:
        raise RunFolderError(f"{path} is not a metrics file a3cqp train wrote (an integer 'update' column on every "
                             f"row): {type(exc).__name__}: {exc}") from None
    text = io.StringIO(newline="")  # (a file without rows gets the header the log appends under, whatever it had)
    w = csv.DictWriter(text, fieldnames=CSV_COLUMNS, restval="nan", extrasaction="ignore")  # older files: NaN columns
    w.writeheader()
    w.writerows(keep)
    write_text_atomic(path, text.getvalue())  # killed mid-write, the run keeps its old file, not half of it


def _tensorboard(out: Path, purge_step: int):
    """A SummaryWriter on OUT/tb when TensorBoard is installed, else None. TensorBoard hides earlier events at steps
    >= `purge_step`: a resumed run passes its checkpoint's step + 1, dropping what a killed run logged after the
    checkpoint, as metrics.csv does."""
    import importlib.util

    if importlib.util.find_spec("tensorboard") is None:  # torch's writer needs the `tensorboard` extra
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(out / "tb"), purge_step=purge_step if purge_step > 1 else None, flush_secs=10)
