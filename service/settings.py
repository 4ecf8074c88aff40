"""The service's settings: :class:`workers.settings.Settings`, the worker's
:class:`~workers.settings.WorkerSettings` plus the API's own knobs, in one class. It lives below
both, in the workers package, which never imports ``service``; :meth:`Settings.env` hands all
of them to a sibling worker process."""

from workers.settings import Settings, WorkerSettings

__all__ = ["Settings", "WorkerSettings"]
