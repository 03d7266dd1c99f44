"""Figures: policy maps (paper Fig. 5), loss curves (Fig. 4), time series with task phases."""

from a3cqp_rl.plotting.loss_curves import plot_loss_curves
from a3cqp_rl.plotting.policy_map import plot_policy_map, policy_grid

__all__ = ["plot_policy_map", "policy_grid", "plot_loss_curves"]
