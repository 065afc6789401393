"""Baseline planners that drive ``ParkingEnv`` in closed loop through its public API."""

from .geometric import GeometricParker, dubins_paths, run_episode
from .hybrid_astar import hybrid_astar
from .hybrid_parker import HybridAStarParker
from .reeds_shepp import reeds_shepp_path

__all__ = ["GeometricParker", "dubins_paths", "run_episode", "HybridAStarParker", "hybrid_astar",
           "reeds_shepp_path"]
