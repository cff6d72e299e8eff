"""The farm: a Celery app, its configuration and thin tasks over `texelbake.pipeline`."""
