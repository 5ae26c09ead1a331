"""Motion generation: point-to-point trajectories and (later) the servo laws."""
