"""The farm's plumbing, shared by the API (`services`) and the Celery workers (`workers`), which
never import each other: the settings (`config`), the database (`db`), the artifact root's
layout (`storage`), sending to the broker (`broker`, `celeryconfig`), the shard ledger
(`ledger`) with its `admission` policy and `resume`, and the local process launcher (`stack`).
No FastAPI here; the queues are the wire contract's table (`schemas.queues`)."""
