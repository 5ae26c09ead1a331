"""Perception: filtering, accumulation and evaluation of point clouds."""
