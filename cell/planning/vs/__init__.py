"""Visual-servoing active vision (visual-servoing paper section II): the entropy NBV objective (eq. 7-9),
the servo loop around the dual-task law of ``cell.control.servo`` (eq. 1-3) and the Local (eq. 4-6),
Global (eq. 10-11) and Hybrid strategies."""
