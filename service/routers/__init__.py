"""One router per resource: health, scenes, enhance, jobs."""
