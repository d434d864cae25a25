"""Robot planning by exhaustive sampling: candidate action sequences, costs, the two-stage scorer, MPC
(paper §IV, §V-C; docs/planner.md)."""
