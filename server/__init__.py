"""ParkSim simulator service: FastAPI app serving renders of scene bundles to planners (``create_app``)."""

import os

# As the ``parksim`` CLI does, before torch loads OpenMP: however the app is started (``parksim serve``,
# uvicorn, a benchmark), waiting OpenMP threads sleep instead of spinning on the cores the renderer needs.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .app import create_app  # noqa: E402
from .settings import Settings  # noqa: E402

__all__ = ["create_app", "Settings"]
