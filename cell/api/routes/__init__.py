"""One router per resource: the cell (status, planners, objects, stop, the arm, the queue), jobs, and
health with metrics."""
