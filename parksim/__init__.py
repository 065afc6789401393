"""ParkSim: surround-view fisheye Gaussian-splatting parking simulator (ParkGaussian)."""

__version__ = "0.1.0"
