"""The fine-tuning worker: the tasks (fine-tuning, camera paths, 3DGS imports), each a short
body run through the job lifecycle of :mod:`jobs.lifecycle`; Huey's consumer and the sweeper
(:mod:`workers.worker`). ``python -m workers`` runs one worker. The job table, layout, settings
and queue it shares with the API live in the ``jobs`` package.
"""
