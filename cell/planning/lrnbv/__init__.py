"""The Low-Resolution NBV planner of the packing paper (Algorithm 1, section 3) and its NBV baseline."""
