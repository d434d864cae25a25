"""Figures (PNG, matplotlib Agg): trajectories, speed/acceleration profiles, Table I, behaviour."""

from .figures import plot_behaviour, plot_profiles, plot_table1, plot_trajectories

__all__ = ["plot_behaviour", "plot_profiles", "plot_table1", "plot_trajectories"]
