"""Health check (compose and the tests wait on it)."""

from __future__ import annotations

from fastapi import APIRouter, Response, status
from sqlalchemy import text

from farm.broker import broker_run_id
from schemas.common import HealthCheck
from services.deps import SessionDep, SettingsDep

router = APIRouter(prefix="/utils", tags=["utils"])


@router.get(
    "/health-check/",
    response_model=HealthCheck,
    operation_id="health_check",
    responses={503: {"model": HealthCheck, "description": "The database is not reachable."}},
)
def health_check(session: SessionDep, settings: SettingsDep, response: Response) -> HealthCheck:
    """Database and broker reachability; 503 when the database is down."""
    try:
        session.execute(text("SELECT 1"))
        db_ok = True
    except Exception:  # noqa: BLE001 - any failure means "not healthy"
        db_ok = False
    broker_ok = broker_run_id(settings.redis_url, timeout=0.5) is not None
    if not db_ok:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    from texelbake import __version__ as version

    return HealthCheck(
        status="ok" if db_ok else "unavailable", database=db_ok, broker=broker_ok, version=version
    )
