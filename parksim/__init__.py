"""ParkSim: surround-view fisheye Gaussian-splatting parking simulator (ParkGaussian)."""

__all__ = ["__version__"]

__version__ = "0.1.0"
