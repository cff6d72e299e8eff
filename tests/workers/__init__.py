"""Tests of the Celery task bodies (workers/)."""
