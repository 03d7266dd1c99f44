"""The pieces of `a2c.train` around its loop: run folder, checkpoints and resume, parameter averaging, Fig. 5 region
checks, and Ctrl-C. Each is a small object the loop calls in one line."""

from __future__ import annotations

import math
import signal
import threading
import warnings
from pathlib import Path

import torch
from torch import Tensor

from a3cqp_rl.checkpoint import load_checkpoint, save_atomic, write_text_atomic
from a3cqp_rl.config import A2CConfig, ExperimentConfig, config_from_dict, config_to_dict
from a3cqp_rl.exceptions import A3CQPError, CheckpointError
from a3cqp_rl.run_folder import RunFolder, RunFolderError, config_changes
from a3cqp_rl.transfer import transfer_margin
from algorithms.networks import ParamLayout, policy_mean
from algorithms.policy import A2CPolicy, layout_key

__all__ = ["open_run_folder", "Checkpoints", "ParameterAverage", "TransferSelection", "RegionChecks", "StopCheckpoint",
           "TrainingInterrupted", "CKPT_KEYS", "RESUMABLE_CHANGES"]

CKPT_KEYS = ("format", "update", "flat", "square_avg", "gen", "rollout", "config", "layout", "metric_sum", "metric_count")
RESUMABLE_CHANGES = ("a2c.total_steps", "a2c.compile", "a2c.checkpoint_every")
"""Config keys a resume may change without --override: how long, whether compiled, how often checkpointed."""


def open_run_folder(out_dir: str | Path | None, *, resume: bool, force: bool) -> RunFolder | None:
    """The locked run folder (None without `out_dir`); a resume needs one that exists."""
    if out_dir is None:
        if resume:
            raise CheckpointError("--resume needs an output directory holding checkpoint.pt")
        return None
    missing = CheckpointError(f"checkpoint not found: {Path(out_dir) / 'checkpoint.pt'} (nothing to resume)")
    if resume and not Path(out_dir).is_dir():
        raise missing
    folder = RunFolder.open(out_dir, resume=resume, force=force)
    if resume and not (Path(out_dir) / "checkpoint.pt").is_file():  # after the lock: a run being written says so
        folder.close()
        raise missing
    return folder


class ParameterAverage:
    """`a2c.average_last` (stochastic weight averaging): the running uniform mean of the parameters over the last
    `fraction` of `num_updates` updates, which policy.pt holds instead of the last parameters."""

    def __init__(self, num_updates: int, fraction: float) -> None:
        """Average the parameters after updates num_updates − ⌈fraction·num_updates⌉ + 1 … num_updates."""
        self.num_updates, self.first = num_updates, num_updates - math.ceil(fraction * num_updates) + 1
        self.mean: Tensor | None = None
        self.count = 0

    def update(self, done_updates: int, flat: Tensor) -> None:
        """Fold in the parameters after update `done_updates` (1-based) if it is inside the window."""
        if done_updates >= self.first:
            self.count += 1
            self.mean = flat.clone() if self.mean is None else self.mean.lerp_(flat, 1.0 / self.count)

    def policy(self, flat: Tensor) -> Tensor:
        """The parameters a saved policy gets now: the average once it has begun, else `flat`."""
        return self.mean if self.count else flat

    def state_dict(self) -> dict:
        """Checkpoint entry (empty before the window)."""
        return {"first": self.first, "count": self.count, "mean": self.mean} if self.count else {}

    def load_state_dict(self, d: dict, start: int) -> None:
        """Restore at checkpoint update `start`; a window moved by another --steps restarts (with a warning if its
        start has passed)."""
        if d and d["first"] == self.first:
            self.count, self.mean = int(d["count"]), d["mean"].clone()
        elif self.first <= start <= self.num_updates:  # (past the end the run is refused: no warning to add)
            warnings.warn(f"a2c.average_last: the average over updates {self.first}-{self.num_updates} cannot be "
                          f"rebuilt from a checkpoint at update {start}; policy.pt averages {start + 1}-{self.num_updates}")


class TransferSelection:
    """`a2c.select_policy` transfer or panda: of the parameters at the log rows in the run's last `a2c.select_last`
    fraction, keeps those with the largest transfer margins (a3cqp_rl.transfer; a later row wins a tie): one for
    transfer, which policy.pt then holds, `a2c.select_candidates` for panda, which algorithms.panda_select runs on
    the Panda after training (`choose`). The rates and the margin of the live parameters go to metrics.csv on every
    row of a per-axis policy (eq. 26 observation, four actions), selecting or not."""

    def __init__(self, layout: ParamLayout, spec, num_updates: int, hp: A2CConfig) -> None:
        """Select over updates num_updates − ⌈select_last·num_updates⌉ + 1 … num_updates if `hp.select_policy` asks."""
        self.layout, self.low, self.high = layout, spec.low, spec.high
        self.applies = layout.obs_dim == 3 and layout.act_dim == 4
        self.enabled = hp.select_policy in ("transfer", "panda")
        if self.enabled and not self.applies:
            raise ValueError(f"a2c.select_policy: {hp.select_policy} needs the per-axis agents' policy (3 observations, "
                             f"4 actions: eq. 26-29), this env's has {layout.obs_dim} and {layout.act_dim}")
        self.keep = hp.select_candidates if hp.select_policy == "panda" else 1
        self.first = num_updates - math.ceil(hp.select_last * num_updates) + 1
        self.candidates: list[tuple[float, int, Tensor]] = []
        """(margin, update, parameters), the largest margin first; a later update first among equal margins."""
        self.chosen = 0
        """Index into `candidates` of the parameters policy.pt holds."""
        self.panda: dict = {}
        """What the Panda trials gave the chosen candidate (select_policy: panda, once `choose` ran)."""

    def __call__(self, done: int, flat: Tensor) -> dict[str, float]:
        """TRANSFER_COLUMNS of the live parameters at log row `done` (empty if the policy is not per-axis); keeps them
        if selecting, inside the window, and their margin is among the `keep` largest so far."""
        if not self.applies:
            return {}
        margin, free, guided = transfer_margin(A2CPolicy(self.layout, flat, self.low, self.high))
        if self.enabled and done >= self.first:
            self.candidates.append((margin, done, flat.clone()))
            self.candidates.sort(key=lambda c: (-c[0], -c[1]))
            del self.candidates[self.keep:]
        return {"transfer_margin": margin, "free_w1": float(free[0]), "free_w2": float(free[1]),
                "guided_w2": float(guided[1]), "guided_fd": float(guided[3])}

    @property
    def best(self) -> Tensor | None:
        """The selected parameters (None before the window)."""
        return self.candidates[self.chosen][2] if self.candidates else None

    @property
    def update(self) -> int:
        """The update after which the selected parameters were logged (0 before the window)."""
        return self.candidates[self.chosen][1] if self.candidates else 0

    @property
    def margin(self) -> float:
        """The selected parameters' transfer margin (−inf before the window)."""
        return self.candidates[self.chosen][0] if self.candidates else -math.inf

    def choose(self, index: int, panda: dict) -> None:
        """Make candidate `index` the one policy.pt holds, with what the Panda trials gave it."""
        self.chosen, self.panda = index, dict(panda)

    def policy(self, flat: Tensor) -> Tensor:
        """The parameters policy.pt gets now: the selected ones once the window has begun, else `flat`."""
        return self.best if self.best is not None else flat

    def meta(self) -> dict:
        """What policy.pt says about the selection (empty when not selecting)."""
        if self.best is None:
            return {}
        return {"selected_update": self.update, "transfer_margin": self.margin,
                **({"panda_selection": self.panda} if self.panda else {})}

    def state_dict(self) -> dict:
        """Checkpoint entry (empty before the window)."""
        return {"first": self.first, "candidates": [(m, u, f) for m, u, f in self.candidates]} \
            if self.candidates else {}

    def load_state_dict(self, d: dict, start: int) -> None:
        """Restore at checkpoint update `start`; a window moved by another --steps keeps the rows it still covers."""
        if not d:
            return
        # checkpoints written before candidates were kept hold the best row alone
        rows = d["candidates"] if "candidates" in d else [(d["margin"], d["update"], d["best"])]
        self.candidates = [(float(m), int(u), f.clone()) for m, u, f in rows if int(u) >= self.first][:self.keep]


class Checkpoints:
    """Everything a run must keep to continue bit-identically: parameters, optimiser, RNG, rollout and env state,
    the metric window, episode count, parameter average and selection; written atomically to OUT/checkpoint.pt."""

    def __init__(self, folder: RunFolder | None, cfg: ExperimentConfig, layout: ParamLayout, spec, flat: Tensor,
                 square_avg: Tensor, gen: torch.Generator, runner, average: ParameterAverage,
                 selection: TransferSelection) -> None:
        """Hold references to the live training state (updated in place by the loop)."""
        self.folder, self.cfg, self.layout, self.spec = folder, cfg, layout, spec
        self.flat, self.square_avg, self.gen, self.runner, self.average = flat, square_avg, gen, runner, average
        self.selection = selection
        self.layout_key = [layout.obs_dim, layout.act_dim, list(layout.hidden), layout.network, layout.critic_obs_dim]
        self.metric_sum = torch.zeros(5)  # running sums of METRICS since the last logged row
        self.metric_count = 0
        self.episodes_before = 0
        """Episodes that ended before the checkpoint this run resumed from, beyond the ones `runner.finished` holds."""

    def begin(self, resume: bool, override: bool, num_updates: int, total_steps: int) -> int:
        """Restore the checkpoint if `resume` (see `restore`), then record the run's config in OUT/config.yaml; returns
        the update to continue after (0 for a new run). A run that already trained more than `num_updates` updates (the
        `total_steps` asked for) is refused before its config.yaml is touched: a plain --resume still continues it."""
        start = self.restore(override) if resume else 0
        if start > num_updates:  # the averaged policy and the logs would be cut back to a shorter run
            per_update = self.cfg.a2c.n_steps * self.runner.num_envs
            raise ValueError(f"the run already trained {start * per_update:,} steps, more than the {total_steps:,} "
                             f"asked for: resume with --steps {start * per_update} or more, or train into a new --out")
        if self.folder is not None:
            self._write_config()
        return start

    @property
    def path(self) -> Path:
        return self.folder.path / "checkpoint.pt"

    def add_metrics(self, metrics: Tensor) -> None:
        """Fold one update's METRICS [5] into the window."""
        self.metric_sum += metrics
        self.metric_count += 1

    def metric_means(self, updates: int) -> Tensor:
        """Means over the window; the window restarts on `log_every` boundaries (a final, partial window stays in the
        sums, so a resumed run re-logs it whole)."""
        means = self.metric_sum / self.metric_count
        if updates % self.cfg.a2c.log_every == 0:
            self.metric_sum.zero_()
            self.metric_count = 0
        return means

    def meta(self) -> dict:
        """What policy.pt and checkpoint.pt say about the network and the env."""
        s = self.spec
        return {"layout": self.layout_key, "config": config_to_dict(self.cfg), "env": self.cfg.env,
                "agents": list(s.agents), "action_low": list(s.low) if s.low is not None else None,
                "action_high": list(s.high) if s.high is not None else None}

    def save(self, update: int) -> None:
        """Write the checkpoint after `update` updates."""
        r = self.runner
        save_atomic({"format": 1, "update": update, "flat": self.flat, "square_avg": self.square_avg,
                     "gen": self.gen.get_state(), "rollout": r.state_dict(), **self.meta(),
                     "finished": [list(x) for x in r.finished[-1000:]], "episodes": self.episodes_before + len(r.finished),
                     "metric_sum": self.metric_sum, "metric_count": self.metric_count,
                     "average": self.average.state_dict(), "selection": self.selection.state_dict()}, self.path)

    def save_policy(self) -> Path:
        """Write OUT/policy.pt: the parameters policy.pt holds (averaged with a2c.average_last or selected with
        a2c.select_policy), layout and bounds."""
        flat = self.selection.policy(self.average.policy(self.flat))
        return save_atomic({"format": 1, "flat": flat.clone(), **self.meta(), "averaged_updates": self.average.count,
                            **self.selection.meta()}, self.folder.path / "policy.pt")

    def restore(self, override: bool) -> int:
        """Load OUT/checkpoint.pt into the live state; refuse a changed config unless `override` (then recorded in
        OUT/overrides.log). Returns the update to continue after."""
        ck = load_checkpoint(self.path, CKPT_KEYS)
        changes = config_changes(_with_defaults(ck["config"]), config_to_dict(self.cfg), RESUMABLE_CHANGES)
        if layout_key(ck["layout"]) != self.layout_key or ck["flat"].shape != self.flat.shape:
            why = (f"; the config differs from the run's ({'; '.join(changes[:4])}{'; ...' if len(changes) > 4 else ''}"
                   "): resume without --config to continue the run as it was recorded" if changes else "")
            raise CheckpointError(f"{self.path} was written for network {ck['layout']}, the config and env ask for "
                                  f"{self.layout_key}{why}")
        start = int(ck["update"])
        if changes and not override:
            raise CheckpointError(f"{self.path} was written with another config ({'; '.join(changes)}); resume with "
                                  "--override to continue with the new values (recorded in overrides.log), or start "
                                  "a new run elsewhere")
        if changes:
            self.folder.record_overrides(start, changes)
        self.flat.copy_(ck["flat"])
        self.square_avg.copy_(ck["square_avg"])
        self.gen.set_state(ck["gen"])
        self.runner.load_state_dict(ck["rollout"])
        self.runner.finished = [tuple(x) for x in ck.get("finished", [])]
        self.episodes_before = int(ck.get("episodes", len(self.runner.finished))) - len(self.runner.finished)
        self.metric_sum, self.metric_count = ck["metric_sum"].clone(), int(ck["metric_count"])
        self.average.load_state_dict(ck.get("average", {}), start)
        self.selection.load_state_dict(ck.get("selection", {}), start)
        return start

    def _write_config(self) -> None:
        import yaml

        path = self.folder.path / "config.yaml"
        try:
            write_text_atomic(path, yaml.safe_dump(config_to_dict(self.cfg), sort_keys=False))
        except OSError as exc:
            raise RunFolderError(f"cannot write {path}: {exc.strerror or exc}") from None


def _with_defaults(d: dict) -> dict:
    """A checkpoint's config with the fields added since it was written at their defaults (as it ran)."""
    try:
        return config_to_dict(config_from_dict(d, "checkpoint config"))
    except A3CQPError:
        return d


class RegionChecks:
    """Paper Fig. 5 region checks (a3cqp_rl.regions) of the policy policy.pt would hold, on every `stride`-th log row
    and the last one (`a2c.region_checks` of them; 0 = none)."""

    def __init__(self, layout: ParamLayout, flat: Tensor, average: ParameterAverage, num_updates: int,
                 hp: A2CConfig) -> None:
        """Check `average.policy(flat)` (read live) over a run of `num_updates` updates."""
        self.layout, self.flat, self.average, self.num_updates, self.log_every = layout, flat, average, num_updates, hp.log_every
        self.stride = max(1, math.ceil(num_updates // hp.log_every / hp.region_checks)) if hp.region_checks else 0

    def __call__(self, done: int) -> dict[str, float]:
        """REGION_COLUMNS values at log row `done` (empty when this row is not checked)."""
        from a3cqp_rl.regions import region_row

        if not self.stride or not (done == self.num_updates or (done // self.log_every) % self.stride == 0):
            return {}
        flat = self.average.policy(self.flat)
        return region_row(lambda o: policy_mean(self.layout, flat, o).clamp(-1.0, 1.0))


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) or SIGTERM stopped training after a checkpoint was written; `signum` says which."""

    def __init__(self, message: str, signum: int = signal.SIGINT) -> None:
        super().__init__(message)
        self.signum = int(signum)


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals that stop training at the next update with a checkpoint: Ctrl-C, and the SIGTERM of `kill`, `timeout`,
a job scheduler's time limit or a container's stop (which follow it with SIGKILL after a grace period)."""


class StopCheckpoint:
    """While active, Ctrl-C (SIGINT) or SIGTERM asks the loop to finish its update, write a checkpoint and stop; a
    second signal interrupts at once (the previous handlers are back)."""

    def __init__(self, enabled: bool) -> None:
        """Install the handlers on `__enter__` if `enabled` and in the main thread (signals go only there)."""
        self.enabled = enabled and threading.current_thread() is threading.main_thread()
        self.requested: int | None = None
        """The signal that asked to stop, None while none came."""
        self._previous: dict[int, object] = {}

    def _handle(self, signum, frame) -> None:  # noqa: ANN001
        self.requested = signum
        self._restore()

    def _restore(self) -> None:
        for sig, handler in self._previous.items():
            if signal.getsignal(sig) == self._handle:
                signal.signal(sig, handler)

    def __enter__(self) -> StopCheckpoint:
        if self.enabled:
            for sig in STOP_SIGNALS:
                previous = signal.getsignal(sig)
                if previous is None:  # set from C: the best we can restore is Python's default
                    previous = signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL
                self._previous[sig] = previous
                signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.enabled:
            self._restore()

    def stop_if_requested(self, step: int, folder: RunFolder | None) -> None:
        """Raise TrainingInterrupted if a stop signal came (call after the checkpoint was written)."""
        if self.requested is not None:
            where = f"; {folder.path / 'checkpoint.pt'} holds it, continue with --resume" if folder else ""
            name = "" if self.requested == signal.SIGINT else f" by {signal.Signals(self.requested).name}"
            raise TrainingInterrupted(f"interrupted{name} at step {step:,}{where}", self.requested)
