"""Next-view planners, selectable per job by name (:mod:`cell.planning.registry`)."""
