"""Paper 000 Fig. 5 regions as numbers: does a learned policy raise the right task where it should?

Each region is a box in the normalised state (|e|/ē, |f_env|/f̄_env, |f_ope|/f̄_ope) with the action the paper
names there (section V, Fig. 5):
  - admittance ẇ2: large operator force, no contact ("the AC task priority w2 tends to rise, while the
    priorities of other tasks decrease");
  - force control ẇ3 and ḟd: contact, no operator, small error (pressing on the workpiece);
  - IK ẇ1: no forces, large error (reaching a target).

Two checks per region, from the policy's mean actions on a grid over the state space:
  - literal (the paper's statement): inside the box the named rate is positive and higher than the other two
    weight rates (for ḟd: positive);
  - contrast: the named action's mean inside exceeds `threshold` and its mean over the rest of the state space
    by 0.1 (it is raised *there* more than elsewhere).
A policy that raises ẇ3 wherever the operator pushes passes the contrast for ẇ2 if ẇ2 is raised there too, but
not the literal check: that is the difference the two columns show.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["FIG5_REGIONS", "RegionResult", "check_fig5_regions", "region_row", "REGION_COLUMNS", "CONTRAST_COLUMNS",
           "LITERAL_COLUMNS", "format_regions"]

# name -> (action index, (e range), (f_env range), (f_ope range))
FIG5_REGIONS: dict[str, tuple[int, tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "w2_admittance_when_operator_pushes": (1, (0.0, 0.3), (0.0, 0.05), (0.5, 1.0)),
    "w3_force_control_in_contact": (2, (0.0, 0.05), (0.3, 1.0), (0.0, 0.05)),
    "fd_desired_force_in_contact": (3, (0.0, 0.05), (0.3, 1.0), (0.0, 0.05)),
    "w1_ik_when_free_with_error": (0, (0.1, 1.0), (0.0, 0.02), (0.0, 0.02)),
}

_SHORT = tuple(name.split("_")[0] for name in FIG5_REGIONS)
CONTRAST_COLUMNS = ("regions_ok", *(f"region_{s}" for s in _SHORT))
"""metrics.csv columns of the contrast check: regions_ok (0-4), then region_w2, _w3, _fd, _w1 (1 = passes)."""
LITERAL_COLUMNS = ("literal_ok", *(f"literal_{s}" for s in _SHORT))
"""metrics.csv columns of the literal check: literal_ok (0-4), then literal_w2, _w3, _fd, _w1 (1 = passes)."""
REGION_COLUMNS = (*CONTRAST_COLUMNS, *LITERAL_COLUMNS)
"""All region columns `region_row` returns."""


@dataclass
class RegionResult:
    """One region: the named action's mean inside and outside the box, all four mean rates inside, both checks."""

    name: str
    inside: float
    """Mean of the named action over the box."""
    outside: float
    """Mean of the named action over the rest of the grid."""
    ok: bool
    """Contrast check: inside > threshold and inside > outside + 0.1."""
    rates_inside: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    """Mean (ẇ1, ẇ2, ẇ3, ḟd) over the box."""
    literal: bool = False
    """Literal check: the named rate > 0 and (for a weight rate) > the other two weight rates, means over the box."""

    @property
    def short(self) -> str:
        """'w2', 'w3', 'fd' or 'w1'."""
        return self.name.split("_")[0]


def _grid(resolution: int) -> Tensor:
    lin = torch.linspace(0.0, 1.0, resolution)
    # denser near zero, where the regions' edges are (|e| of a few cm, small forces)
    lin = torch.unique(torch.cat([lin, torch.tensor([0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.1, 0.2, 0.3])]))
    e, fe, fo = torch.meshgrid(lin, lin, lin, indexing="ij")
    return torch.stack([e, fe, fo], -1).reshape(-1, 3)


def check_fig5_regions(policy: Callable[[Tensor], Tensor], threshold: float = 0.3, resolution: int = 21) -> list[RegionResult]:
    """Evaluate `policy` (obs [..., 3] -> mean action [..., 4] in [-1, 1]) on a grid: both checks for each region."""
    obs = _grid(resolution)
    act = policy(obs).float()
    if act.shape != (obs.shape[0], 4):
        raise ValueError(f"policy must map observations [B, 3] to actions [B, 4], got {tuple(act.shape)}")
    out = []
    for name, (i, er, fer, for_) in FIG5_REGIONS.items():
        inside = ((obs[:, 0] >= er[0]) & (obs[:, 0] <= er[1]) & (obs[:, 1] >= fer[0]) & (obs[:, 1] <= fer[1])
                  & (obs[:, 2] >= for_[0]) & (obs[:, 2] <= for_[1]))
        rates = act[inside].mean(0)
        a_in, a_out = rates[i].item(), act[~inside, i].mean().item()
        others = [rates[k].item() for k in range(3) if k != i] if i < 3 else []
        literal = a_in > 0.0 and all(a_in > o for o in others)
        out.append(RegionResult(name, a_in, a_out, a_in > threshold and a_in - a_out > 0.1,
                                tuple(float(r) for r in rates.tolist()), literal))
    return out


def region_row(policy: Callable[[Tensor], Tensor]) -> dict[str, float]:
    """`check_fig5_regions` as REGION_COLUMNS values: per check, the number of regions that pass, then 1.0 / 0.0 each."""
    results = check_fig5_regions(policy)
    contrast = [float(sum(r.ok for r in results)), *(float(r.ok) for r in results)]
    literal = [float(sum(r.literal for r in results)), *(float(r.literal) for r in results)]
    return dict(zip(REGION_COLUMNS, contrast + literal))


_LABELS = {"w2": "w2 admittance", "w3": "w3 force control", "fd": "fd desired force", "w1": "w1 IK"}


def format_regions(results: list[RegionResult]) -> str:
    """Both checks as a small text table: one line per region (mean rates inside, literal, contrast)."""
    lines = [f"Fig. 5 regions: literal {sum(r.literal for r in results)}/4, contrast {sum(r.ok for r in results)}/4",
             f"  {'region':<17} {'mean (w1, w2, w3, fd) inside':<30} {'literal':<8} contrast (inside/outside)"]
    for r in results:
        rates = ", ".join(f"{v:+.2f}" for v in r.rates_inside)
        lines.append(f"  {_LABELS[r.short]:<17} ({rates})   {'ok' if r.literal else 'no':<8} "
                     f"{r.inside:+.2f}/{r.outside:+.2f} {'ok' if r.ok else 'no'}")
    return "\n".join(lines)
