"""Safety: the motion guard, the one place where motion commands reach an arm."""
