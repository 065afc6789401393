"""ParkSim simulator service: FastAPI app serving renders of scene bundles to planners (``create_app``)."""

from parksim.omp_env import prefer_sleeping_omp_threads

prefer_sleeping_omp_threads()   # as the CLI does, however the app is started (parksim serve, uvicorn, a benchmark)

from .app import create_app  # noqa: E402
from .settings import Settings  # noqa: E402

__all__ = ["create_app", "Settings"]
