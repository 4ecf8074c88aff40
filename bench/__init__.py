"""Measurements of the library, the fitter and the service; run each as ``python -m bench.NAME``
from the repository root (``./dev python -m bench.NAME``). Every script writes CSV/JSON and a
plot stamped with the date, the machine and the commit (``bench.common.stamp``)."""

# First, before any bench module imports torch: importing roguenerf sets OpenMP's wait policy,
# which must happen before torch loads.
import roguenerf  # noqa: F401
