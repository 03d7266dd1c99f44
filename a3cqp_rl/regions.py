"""Paper 000 Fig. 5 regions as numbers: does a learned policy raise the right task where it should?

Each region is a box in the normalised state (|e|/ē, |f_env|/f̄_env, |f_ope|/f̄_ope). For each
(region, action) pair the mean action over the box must exceed `threshold` and the mean over the
rest of the state space (the contrast):
  - admittance ẇ2: large operator force, no contact (the operator guides the robot);
  - force control ẇ3 and ḟd: contact, no operator, small error (pressing on the workpiece);
  - IK ẇ1: no forces, large error (reaching a target).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

# name -> (action index, (e range), (f_env range), (f_ope range))
FIG5_REGIONS: dict[str, tuple[int, tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "w2_admittance_when_operator_pushes": (1, (0.0, 0.3), (0.0, 0.05), (0.5, 1.0)),
    "w3_force_control_in_contact": (2, (0.0, 0.05), (0.3, 1.0), (0.0, 0.05)),
    "fd_desired_force_in_contact": (3, (0.0, 0.05), (0.3, 1.0), (0.0, 0.05)),
    "w1_ik_when_free_with_error": (0, (0.1, 1.0), (0.0, 0.02), (0.0, 0.02)),
}


REGION_COLUMNS = ("regions_ok", *(f"region_{name.split('_')[0]}" for name in FIG5_REGIONS))
"""metrics.csv columns of `region_row`: regions_ok (0-4), then region_w2, region_w3, region_fd, region_w1 (1 = passes)."""


@dataclass
class RegionResult:
    """Mean action inside a region and over the rest of the state space."""

    name: str
    inside: float
    outside: float
    ok: bool


def check_fig5_regions(policy: Callable[[Tensor], Tensor], threshold: float = 0.3, resolution: int = 21) -> list[RegionResult]:
    """Evaluate `policy` (obs [..., 3] -> action [..., 4]) on a grid; a region passes if inside > threshold and > outside + 0.1."""
    lin = torch.linspace(0.0, 1.0, resolution)
    # denser near zero, where the regions' edges are (|e| of a few cm, small forces)
    lin = torch.unique(torch.cat([lin, torch.tensor([0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.1, 0.2, 0.3])]))
    e, fe, fo = torch.meshgrid(lin, lin, lin, indexing="ij")
    obs = torch.stack([e, fe, fo], -1).reshape(-1, 3)
    act = policy(obs)
    out = []
    for name, (i, er, fer, for_) in FIG5_REGIONS.items():
        inside = ((obs[:, 0] >= er[0]) & (obs[:, 0] <= er[1]) & (obs[:, 1] >= fer[0]) & (obs[:, 1] <= fer[1])
                  & (obs[:, 2] >= for_[0]) & (obs[:, 2] <= for_[1]))
        a_in, a_out = act[inside, i].mean().item(), act[~inside, i].mean().item()
        out.append(RegionResult(name, a_in, a_out, a_in > threshold and a_in - a_out > 0.1))
    return out


def region_row(policy: Callable[[Tensor], Tensor]) -> dict[str, float]:
    """`check_fig5_regions` as REGION_COLUMNS values: the number of regions that pass, then 1.0 / 0.0 per region."""
    results = check_fig5_regions(policy)
    return dict(zip(REGION_COLUMNS, [float(sum(r.ok for r in results)), *(float(r.ok) for r in results)]))
