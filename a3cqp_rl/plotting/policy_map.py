"""Policy maps like paper 000 Fig. 5: each action (ẇ1, ẇ2, ẇ3, ḟd) as a heat map over two
normalised state variables, the third held at chosen levels; colour scale fixed to [-1, 1]."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

STATE_NAMES = ("e", "f_env", "f_ope")
STATE_LABELS = {"e": r"$|e|/\bar e$", "f_env": r"$|f_{env}|/\bar f_{env}$", "f_ope": r"$|f_{ope}|/\bar f_{ope}$"}
ACTION_LABELS = (r"$\dot w_1$ (IK)", r"$\dot w_2$ (admittance)", r"$\dot w_3$ (force control)", r"$\dot f_d$")


def policy_grid(
    policy: Callable[[Tensor], Tensor], x: str = "f_ope", y: str = "f_env", fixed: str = "e", level: float = 0.0,
    resolution: int = 41,
) -> tuple[Tensor, Tensor, Tensor]:
    """Evaluate `policy` on a [resolution²] grid of (x, y) in [0, 1]² with `fixed` = level: (xs, ys, actions [R, R, 4])."""
    if sorted((x, y, fixed)) != sorted(STATE_NAMES):
        raise ValueError(f"x, y, fixed must be a permutation of {STATE_NAMES}, got {(x, y, fixed)}")
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"level must be in [0, 1] (normalised state), got {level}")
    lin = torch.linspace(0.0, 1.0, resolution)
    gy, gx = torch.meshgrid(lin, lin, indexing="ij")
    cols = {x: gx, y: gy, fixed: torch.full_like(gx, level)}
    obs = torch.stack([cols[n] for n in STATE_NAMES], dim=-1)  # [R, R, 3] in (e, f_env, f_ope) order
    with torch.no_grad():
        act = policy(obs)
    if act.shape[-1] != len(ACTION_LABELS):
        raise ValueError(f"the policy gives {act.shape[-1]} action(s) per observation; a policy map draws the A3CQP "
                         f"policy's {len(ACTION_LABELS)} (ẇ1, ẇ2, ẇ3, ḟd)")
    return lin, lin, act


def plot_policy_map(
    policy: Callable[[Tensor], Tensor],
    out: str | Path,
    x: str = "f_ope",
    y: str = "f_env",
    fixed: str = "e",
    levels: Sequence[float] = (0.0, 0.05, 0.3),
    resolution: int = 41,
    title: str = "policy",
) -> Path:
    """Draw `policy` (obs [..., 3] -> action [..., 4], e.g. algorithms.a2c.load_policy(path)) as a 4 × len(levels)
    grid of heat maps (one row per action) to `out` (.png or .pdf); returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, len(levels), figsize=(3.2 * len(levels) + 1.2, 11), squeeze=False,
                             sharex=True, sharey=True, constrained_layout=True)
    im = None
    for j, level in enumerate(levels):
        xs, ys, act = policy_grid(policy, x, y, fixed, level, resolution)
        for i in range(4):
            ax = axes[i][j]
            im = ax.pcolormesh(xs.numpy(), ys.numpy(), act[..., i].numpy(), vmin=-1, vmax=1, cmap="viridis",
                               shading="nearest")
            if i == 0:
                ax.set_title(f"{STATE_LABELS[fixed]} = {level:g}")
            if j == 0:
                ax.set_ylabel(f"{ACTION_LABELS[i]}\n{STATE_LABELS[y]}")
            if i == 3:
                ax.set_xlabel(STATE_LABELS[x])
    fig.colorbar(im, ax=axes, shrink=0.6, label="action (rate of change)")
    fig.suptitle(f"Policy map (paper Fig. 5 layout): {title}", fontsize=9)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
