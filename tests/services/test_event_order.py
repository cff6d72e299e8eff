"""The event streams read only up to the settled mark (`services.event_order`): an event whose
transaction commits after a later seq's is still sent, in order, and a rolled-back sequence
value stops the streams only until it is stale. The concurrent case on a real PostgreSQL,
where sequence order and commit order differ."""

from __future__ import annotations

import time
from datetime import datetime, timedelta

import pytest

from farm.db import Asset, Event, Job, session_factory, utcnow
from services.event_order import SettledMark
from services.routers.events import tenant_events_after
from services.routers.jobs import _events_after
from tests.helpers.service import fresh_postgres

T0 = datetime(2026, 1, 1)


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_settle_stops_at_a_fresh_gap_and_steps_over_a_stale_one():
    clock = Clock()
    mark = SettledMark(stale_seconds=5.0, clock=clock)
    now = T0 + timedelta(seconds=100)
    fresh = now - timedelta(seconds=1)
    assert mark.settle([(1, fresh), (2, fresh), (3, fresh)], 0, now) == (3, False)
    assert mark.settle([], 7, now) == (7, False)
    # 5 is missing and 6 was stamped 1 s ago: 5 may still commit
    assert mark.settle([(4, fresh), (6, fresh), (7, fresh)], 3, now) == (4, True)
    # the event after the gap is older than the threshold: 5 is taken as rolled back
    old = now - timedelta(seconds=6)
    assert mark.settle([(4, old), (6, old), (7, fresh)], 3, now) == (7, False)
    # a gap this stream has waited at for the threshold is stale whatever the stamps say
    # (a writer whose clock runs ahead)
    ahead = now + timedelta(seconds=60)
    assert mark.settle([(6, ahead)], 4, now) == (4, True)
    clock.t = 4.9
    assert mark.settle([(6, ahead)], 4, now) == (4, True)
    clock.t = 5.0
    assert mark.settle([(6, ahead)], 4, now) == (6, False)
    # two gaps: the first stale, the second fresh
    assert mark.settle([(10, old), (12, fresh)], 8, now) == (10, True)


@pytest.fixture
def pg():
    with fresh_postgres() as url:
        sm = session_factory(url)
        with sm() as s:
            s.add(Asset(id="a", tenant="t", sha256="0" * 64, filename="x.usda", kind="usda",
                        root_layer="x.usda", size_bytes=1, n_files=1))
            s.add_all([Job(id=j, tenant="t", asset_id="a", settings_json="{}") for j in "JK"])
            s.commit()
        yield sm


def _event(s, job: str, kind: str = "job") -> int:
    ev = Event(job_id=job, kind=kind, data_json="{}")
    s.add(ev)
    s.flush()
    return int(ev.seq)


def test_an_event_committed_after_a_later_seq_is_sent_in_order(pg):
    mark = SettledMark()
    slow, fast = pg(), pg()
    first = _event(slow, "J")  # in flight: its seq is taken, its commit comes last
    second = _event(fast, "K")
    fast.commit()
    assert second > first
    rows, upto = tenant_events_after(pg, "t", 0, mark)
    assert rows == [] and upto == first - 1  # not past the event in flight
    # the per-job stream of the job whose event committed: held, so a terminal state would
    # not end it before the event below the mark arrives
    with pg() as s:
        s.get(Job, "K").state = "succeeded"
        s.commit()
    rows, state, upto, held = _events_after(pg, "K", 0, mark)
    assert (rows, state, held) == ([], "succeeded", True)
    slow.commit()
    rows, upto = tenant_events_after(pg, "t", 0, mark)
    assert [e.seq for e in rows] == [first, second] and upto == second
    rows, state, upto, held = _events_after(pg, "K", 0, mark)
    assert [e.seq for e in rows] == [second] and not held
    slow.close()
    fast.close()


def test_a_rolled_back_seq_holds_the_streams_only_until_stale(pg):
    mark = SettledMark(stale_seconds=0.5)
    lost = pg()
    gone = _event(lost, "J")
    lost.rollback()  # the sequence value is used and will never appear
    with pg() as s:
        after = _event(s, "J")
        s.commit()
    assert after > gone
    rows, upto = tenant_events_after(pg, "t", 0, mark)
    assert rows == [] and upto == gone - 1
    time.sleep(0.6)
    rows, upto = tenant_events_after(pg, "t", 0, mark)
    assert [e.seq for e in rows] == [after]
    # a stream that starts later sees the old gap as stale at once (the stamp after it)
    late = SettledMark(stale_seconds=0.5)
    assert tenant_events_after(pg, "t", 0, late)[0][0].seq == after
    assert utcnow() - rows[0].at >= timedelta(seconds=0.5)
    lost.close()
