"""Baseline planners that drive ``ParkingEnv`` in closed loop through its public API."""

from .geometric import GeometricParker, dubins_paths, run_episode

__all__ = ["GeometricParker", "dubins_paths", "run_episode"]
