"""Robot planning by exhaustive sampling (paper §IV, §V-C; docs/planner.md): candidate action
sequences and their kinematics (candidates, steering), costs, the two-stage planner, the driving
styles' rules (styles) and the receding-horizon policy (mpc)."""
