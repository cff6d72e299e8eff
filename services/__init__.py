"""The texelbake HTTP service (FastAPI): routes, auth, upload handling, the job store."""
