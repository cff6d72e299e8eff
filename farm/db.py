"""The job store: SQLAlchemy tables for tokens, assets, jobs, stages, the shard ledger and events.

SQLite by default (WAL, a busy timeout so several worker processes can write), PostgreSQL by URL.
Job state lives here, never only in the broker: the broker only moves work.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

from sqlalchemy import (
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    create_engine,
    event,
    text,
)
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.exc import (
    DBAPIError,
    IntegrityError,
    OperationalError,
    ProgrammingError,
)
from sqlalchemy.exc import TimeoutError as SATimeoutError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker

T = TypeVar("T")


def utcnow() -> datetime:
    return datetime.now(UTC).replace(tzinfo=None)


class Base(DeclarativeBase):
    pass


class ApiToken(Base):
    __tablename__ = "api_tokens"
    digest: Mapped[str] = mapped_column(String(64), primary_key=True)  # HMAC-SHA256(secret, token)
    tenant: Mapped[str] = mapped_column(String(128), index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Asset(Base):
    __tablename__ = "assets"
    __table_args__ = (UniqueConstraint("tenant", "sha256", name="uq_asset_tenant_sha"),)
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    tenant: Mapped[str] = mapped_column(String(128), index=True)
    sha256: Mapped[str] = mapped_column(String(64))
    filename: Mapped[str] = mapped_column(String(255))
    kind: Mapped[str] = mapped_column(String(8))
    root_layer: Mapped[str] = mapped_column(String(1024))
    size_bytes: Mapped[int] = mapped_column(Integer)
    n_files: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Job(Base):
    __tablename__ = "jobs"
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    tenant: Mapped[str] = mapped_column(String(128), index=True)
    asset_id: Mapped[str] = mapped_column(ForeignKey("assets.id"))
    settings_json: Mapped[str] = mapped_column(Text)
    state: Mapped[str] = mapped_column(String(16), default="queued", index=True)
    #: 0..100, higher first: the ledger admits shards to the broker by priority
    priority: Mapped[int] = mapped_column(Integer, default=50, server_default="50")
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    skipped_json: Mapped[str] = mapped_column(Text, default="[]")
    plan_sent: Mapped[bool] = mapped_column(Boolean, default=False)
    broker_run_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)


class Stage(Base):
    __tablename__ = "stages"
    __table_args__ = (UniqueConstraint("job_id", "name", name="uq_stage"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"), index=True)
    name: Mapped[str] = mapped_column(String(32))
    position: Mapped[int] = mapped_column(Integer)
    queue: Mapped[str] = mapped_column(String(32))
    depends_on_json: Mapped[str] = mapped_column(Text, default="[]")
    n_shards: Mapped[int] = mapped_column(Integer)
    state: Mapped[str] = mapped_column(String(16), default="pending")
    started_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)


class Shard(Base):
    """The shard ledger: one row per (job, stage, shard)."""

    __tablename__ = "shards"
    __table_args__ = (
        UniqueConstraint("job_id", "stage", "shard", name="uq_shard"),
        Index("ix_shard_state", "state"),
    )
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"), index=True)
    stage: Mapped[str] = mapped_column(String(32))
    shard: Mapped[int] = mapped_column(Integer)
    queue: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16), default="pending")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    completions: Mapped[int] = mapped_column(Integer, default=0)
    lost: Mapped[int] = mapped_column(Integer, default=0)  # deliveries that died mid-shard
    task_id: Mapped[str | None] = mapped_column(String(128), nullable=True)
    sent: Mapped[bool] = mapped_column(Boolean, default=False)
    broker_run_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    enqueued_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    started_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    seconds: Mapped[float | None] = mapped_column(Float, nullable=True)
    worker: Mapped[str | None] = mapped_column(String(255), nullable=True)
    artifact_key: Mapped[str | None] = mapped_column(String(1024), nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)


class Batch(Base):
    """A batch (`POST /batches`): its defaults; its items are `BatchItem` rows, one job each."""

    __tablename__ = "batches"
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    tenant: Mapped[str] = mapped_column(String(128), index=True)
    name: Mapped[str | None] = mapped_column(String(200), nullable=True)
    settings_json: Mapped[str] = mapped_column(Text)  # the batch's default settings
    priority: Mapped[int] = mapped_column(Integer, default=50)
    n_items: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class BatchItem(Base):
    """Item `position` of a batch: the job made for it (job state is the item's state)."""

    __tablename__ = "batch_items"
    __table_args__ = (UniqueConstraint("batch_id", "position", name="uq_batch_item"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    batch_id: Mapped[str] = mapped_column(ForeignKey("batches.id"), index=True)
    position: Mapped[int] = mapped_column(Integer)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"), unique=True)


class Event(Base):
    __tablename__ = "events"
    # a job's newest event in one index probe (the status cache's version: `max(seq)`)
    __table_args__ = (Index("ix_event_job_seq", "job_id", "seq"),)
    seq: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(String(64), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    data_json: Mapped[str] = mapped_column(Text)
    at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


_engines: dict[tuple[str, str], Engine] = {}
_lock = threading.RLock()

#: engine roles: `write` (ledger transitions; SQLite `BEGIN IMMEDIATE`), `read` (the API's
#: reads in worker threads), `inline` (the reads the API's event loop awaits, on its own threads)
ROLES = ("write", "read", "inline")

#: PostgreSQL pools per role: (pool_size, max_overflow). The API runs sync routes in anyio's
#: thread pool (40 threads); a route holds at most one read and one write connection, and the
#: writes are short transactions, so 20 each cover it without taking half of a default server's
#: `max_connections` (100) from one process. The inline role serves the event loop's reads,
#: which run on two threads of their own (`services.status_cache.LoopReads`): a pool of its own
#: that thread-held connections can never exhaust.
PG_POOLS = {"write": (5, 15), "read": (5, 15), "inline": (2, 2)}


def get_engine(url: str, *, readonly: bool = False, role: str | None = None) -> Engine:
    """One engine per (URL, role) per process; tables created on first use.

    SQLite: writers open `BEGIN IMMEDIATE` so a read-then-write transaction (the conditional
    ledger updates) waits for the lock instead of failing with a stale WAL snapshot; the
    read roles keep deferred transactions so reads never queue on writers (WAL). The pool has
    no upper bound (a SQLite connection is a file handle, not a server slot): a bounded pool
    was exhausted by requests waiting for the write lock, and a read on the event loop then
    blocked the whole API for the pool timeout (benchmarks/load.py).
    PostgreSQL: the read roles run in autocommit (each read is one statement: no BEGIN and no
    ROLLBACK round trips); the inline role skips the pre-ping round trip too (its callers retry
    once on a dropped connection: `retry_disconnect`).
    """
    role = role or ("read" if readonly else "write")
    if role not in ROLES:
        raise ValueError(f"unknown engine role {role!r}; expected one of {ROLES}")
    key = (url, role)
    with _lock:
        eng = _engines.get(key)
        if eng is not None:
            return eng
        if url.startswith("sqlite"):
            db_file = make_url(url).database
            if db_file and db_file != ":memory:":  # a worker may start before the API
                Path(db_file).parent.mkdir(parents=True, exist_ok=True)
            eng = create_engine(
                url,
                connect_args={"timeout": 60, "check_same_thread": False},
                pool_size=8,
                max_overflow=-1,
            )
            immediate = role == "write"

            @event.listens_for(eng, "connect")
            def _sqlite_connect(dbapi_conn, _record):  # noqa: ANN001
                dbapi_conn.isolation_level = None  # we emit BEGIN ourselves
                cur = dbapi_conn.cursor()
                cur.execute("PRAGMA journal_mode=WAL")
                cur.execute("PRAGMA synchronous=NORMAL")
                cur.execute("PRAGMA busy_timeout=60000")
                cur.close()

            @event.listens_for(eng, "begin")
            def _sqlite_begin(conn):  # noqa: ANN001
                conn.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")
        else:
            size, overflow = PG_POOLS[role]
            kw: dict = {"pool_size": size, "max_overflow": overflow, "pool_timeout": 10}
            if role == "write":
                kw["pool_pre_ping"] = True
            else:
                kw["isolation_level"] = "AUTOCOMMIT"
                kw["pool_pre_ping"] = role == "read"
            eng = create_engine(url, **kw)
        if role == "write":
            _create_tables(eng)
        else:
            get_engine(url)  # make sure the tables exist
        _engines[key] = eng
        return eng


#: columns and indexes added after a table's first release: (table, column, DDL type)
_ADDED_COLUMNS = (("jobs", "priority", "INTEGER NOT NULL DEFAULT 50"),)
_ADDED_INDEXES = (("ix_event_job_seq", "events", "job_id, seq"),)


def _upgrade(eng: Engine) -> None:
    """Bring a database made by an older texelbake up to date (`create_all` only makes
    missing tables): add the columns and indexes of `_ADDED_*`, idempotently."""
    from sqlalchemy import inspect

    with eng.begin() as c:
        insp = inspect(c)
        for table, column, ddl in _ADDED_COLUMNS:
            if column not in {col["name"] for col in insp.get_columns(table)}:
                c.exec_driver_sql(f"ALTER TABLE {table} ADD COLUMN {column} {ddl}")
        for name, table, cols in _ADDED_INDEXES:
            c.exec_driver_sql(f"CREATE INDEX IF NOT EXISTS {name} ON {table} ({cols})")


def _create_tables(eng: Engine, tries: int = 5) -> None:
    """create_all, tolerating a concurrent process creating the same tables first."""
    for i in range(tries):
        try:
            Base.metadata.create_all(eng)
            _upgrade(eng)
            return
        except (IntegrityError, ProgrammingError, OperationalError):
            if i == tries - 1:
                raise
            time.sleep(0.2 * (i + 1))


def session_factory(url: str, *, readonly: bool = False, role: str | None = None) -> sessionmaker:
    return sessionmaker(bind=get_engine(url, readonly=readonly, role=role), expire_on_commit=False)


def relaxed_commit(s: Session) -> None:
    """Let this transaction's commit return before its WAL record is flushed to disk
    (PostgreSQL `synchronous_commit = off` for this transaction; nothing on SQLite, whose
    writers use `synchronous=NORMAL`). Only for writes whose loss in a database crash is
    repaired by the ledger itself: the marks that a message was sent (the sweeper sends an
    unmarked message again, and every task is idempotent). A flush cost a submission 4 ms
    median and 12 ms p90 on a loaded 2-core machine."""
    if s.get_bind().dialect.name == "postgresql":
        s.execute(text("SET LOCAL synchronous_commit TO OFF"))


def retry_disconnect(fn: Callable[[], T]) -> T:
    """`fn()`, once more if the database dropped the connection (a restarted PostgreSQL: the
    pool is invalidated on the first error, the retry gets a fresh connection)."""
    try:
        return fn()
    except DBAPIError as exc:
        if not exc.connection_invalidated:
            raise
        return fn()


def is_locked(exc: BaseException) -> bool:
    """SQLite's busy timeout ran out (`database is locked`), or a pool had no connection."""
    return isinstance(exc, SATimeoutError) or (
        isinstance(exc, OperationalError) and "database is locked" in str(exc)
    )


def dispose_engines() -> None:
    """Drop pooled connections (after fork in a worker child)."""
    with _lock:
        for eng in _engines.values():
            eng.dispose(close=False)
