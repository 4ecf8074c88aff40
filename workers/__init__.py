"""Fine-tuning workers: the job table (the truth), Huey wiring, the sweeper and the task.
``python -m workers`` runs one worker."""
