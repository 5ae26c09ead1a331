"""Scan jobs: set-up, the loop, termination, the job folder."""
