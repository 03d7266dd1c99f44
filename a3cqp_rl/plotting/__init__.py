"""Figures: policy maps (paper Fig. 5), loss curves (Fig. 4), Fig. 5 regions and the Panda transfer checks over
training, time series with task phases."""

from a3cqp_rl.plotting.loss_curves import plot_loss_curves
from a3cqp_rl.plotting.policy_map import plot_policy_map, policy_grid
from a3cqp_rl.plotting.episode import load_episode, plot_episode, render_strip
from a3cqp_rl.plotting.region_history import plot_region_history, region_history
from a3cqp_rl.plotting.transfer_history import plot_transfer_history

__all__ = ["plot_policy_map", "policy_grid", "plot_loss_curves", "plot_region_history", "region_history",
           "plot_transfer_history", "plot_episode", "load_episode", "render_strip"]
