"""The Celery workers: the app (configured by `farm.celeryconfig`) and thin tasks over
`texelbake.pipeline`."""
