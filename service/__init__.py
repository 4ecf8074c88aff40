"""The RoGUENeRF HTTP service (FastAPI). ``service.app.create_app`` builds the app;
``service.server.run`` serves it with an embedded worker. Nothing heavy runs at import."""

from roguenerf.runtime import prefer_passive_wait as _prefer_passive_wait

# The API and the worker share the machine: OpenMP threads should sleep, not spin, while
# waiting (bench/threads.py). Effective only if torch is not imported yet; a user's
# OMP_WAIT_POLICY wins.
_prefer_passive_wait()
