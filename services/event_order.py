"""Events in the order they can no longer change: the event streams' read cursor.

An event's `seq` comes from the database's sequence when its transaction inserts it, not when
it commits. Under PostgreSQL two ledger transactions (a worker's shard and the API's job, or
two workers) can commit in the other order: seq 11 is visible while seq 10 is still in
flight. A stream that sends 11 and then reads `seq > 11` would never send 10. SQLite has one
writer at a time, so there the sequence never runs ahead of the commits.

A stream therefore reads only up to the *settled* mark: the last seq before the first open
gap in the whole table's sequence after its cursor (the event of every seq up to it is
committed, or will never be). A gap is a transaction still in flight, or a sequence value its
transaction rolled back and that will never appear. A gap is open for `STALE_SECONDS`: until
the event after it is that old (its `at`, stamped at insert: a transaction holding the
missing value inserted it before), or, whatever the clocks say, until this stream has seen
it that long. Then the mark steps over it. A transaction that holds an inserted event longer
than that can still be missed; the ledger's transactions take milliseconds. This is the
"high-water mark with a stale threshold" of event stores on PostgreSQL (Marten's
HighWaterMarkDetector); the gap test reads the sequence and the stamps, no event bodies.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from datetime import datetime, timedelta

from sqlalchemy import Select, select
from sqlalchemy.orm import Session

from farm.db import Event, utcnow

#: seconds a gap in the sequence is waited for before it is taken as a rolled-back value
STALE_SECONDS = 5.0
#: sequence values read per look for gaps
SCAN = 2000


class SettledMark:
    """One stream's view of the settled mark. `clock`: seconds, monotonic (tests pass their
    own)."""

    def __init__(self, stale_seconds: float = STALE_SECONDS,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.stale = float(stale_seconds)
        self.clock = clock
        self._seen: dict[int, float] = {}  # first missing seq of a gap -> when first seen

    def settle(self, rows: list[tuple[int, datetime]], after: int,
               now: datetime | None = None) -> tuple[int, bool]:
        """(mark, held) from the committed (seq, at) after `after`, in increasing seq: mark
        the last seq before the first open gap (every seq of (after, mark] is committed or
        stale), held whether an open gap stops it before the last of `rows`. `now`: the
        stamps' clock (UTC, naive, as `farm.db.utcnow`)."""
        mono = self.clock()
        now = utcnow() if now is None else now
        stale = timedelta(seconds=self.stale)
        expect = after + 1
        held = False
        for seq, at in rows:  # a loop over sequence values: stops at the first open gap
            if seq > expect:
                first = self._seen.setdefault(expect, mono)
                if now - at < stale and mono - first < self.stale:
                    held = True
                    break
            expect = seq + 1
        self._seen = {k: v for k, v in self._seen.items() if k >= expect}
        return expect - 1, held

    def read(self, session: Session, after: int) -> tuple[int, bool]:
        """`settle` over the table's committed events after `after` (at most SCAN), read in
        `session`."""
        rows = session.execute(select(Event.seq, Event.at).where(Event.seq > after)
                               .order_by(Event.seq).limit(SCAN)).all()
        return self.settle([(int(q), at) for q, at in rows], after)


def events_upto(session: Session, mark: SettledMark, query: Select, after: int, limit: int
                ) -> tuple[list[Event], int, bool]:
    """`query`'s events (a `select(Event)` with the stream's filters) in (after, settled], at
    most `limit`, in seq order; the stream's next cursor (the settled mark, or the last event
    read when `limit` cut the read short); and whether an open gap holds the mark."""
    upto, held = mark.read(session, after)
    rows = list(session.scalars(query.where(Event.seq > after, Event.seq <= upto)
                                .order_by(Event.seq).limit(limit)).all())
    return rows, (upto if len(rows) < limit else rows[-1].seq), held
