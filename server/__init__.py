"""ParkSim simulator service: FastAPI app serving renders of scene bundles to planners (``create_app``)."""

from .app import create_app
from .settings import Settings

__all__ = ["create_app", "Settings"]
