"""The job domain that the API (``service``) and the workers (``workers``) share, below both:
the job and scene table (:mod:`jobs.db`, :mod:`jobs.store`), the data directory's layout
(:mod:`jobs.layout`), the settings both processes read (:mod:`jobs.settings`), the queue
(:mod:`jobs.queue`), the data directory as a process opens it and the checkpoint a scene's
version means (:mod:`jobs.data`), and the one lifecycle of a running job (:mod:`jobs.lifecycle`:
claim, heartbeat, progress, and how it ends: succeeded, failed, cancelled, requeued or lost).

It imports only itself and the library's public names (``from roguenerf import ...``, lazily
where torch would load); ``service`` and ``workers`` import it and never each other.
"""
