"""The texelbake HTTP service (FastAPI): routes, auth, upload handling; the farm's shared
plumbing (settings, database, ledger) is `farm`."""
