"""The nlpsf web service: a thin FastAPI layer over the ``nlpsf`` library (no physics here)."""
