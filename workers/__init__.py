"""Fine-tuning workers: the job table (the truth), Huey wiring, the sweeper and the task.
``python -m workers`` runs one worker."""

from roguenerf.runtime import prefer_passive_wait as _prefer_passive_wait

# The API and the worker share the machine: OpenMP threads should sleep, not spin, while
# waiting (bench/threads.py). Effective only if torch is not imported yet; a user's
# OMP_WAIT_POLICY wins.
_prefer_passive_wait()
