"""The service's settings: :class:`workers.settings.Settings` (one class for the API and the
workers; it lives below both, in the workers package, which never imports ``service``)."""

from workers.settings import Settings

__all__ = ["Settings"]
