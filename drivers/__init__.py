"""Hardware behind small interfaces: arms, depth sensors, robot models and their simulated backends.

This package never imports ``cell``; the application talks to hardware only through the interfaces here.
"""
