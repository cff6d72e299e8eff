"""The shard ledger's transitions on SQLite and PostgreSQL: fan-out/fan-in, exactly-once
promotion under concurrent finishes, the redelivery cap, the sweeper, cancel."""

from __future__ import annotations

import threading
from datetime import timedelta

import pytest
from sqlalchemy import select

from services import ledger
from services.db import Asset, Job, Shard, session_factory, utcnow
from tests.svc_util import fresh_postgres

PLAN = [
    ("ingest", "ingest", 1, ()),
    ("cpm", "cpm", 6, ("ingest",)),
    ("avis", "avis", 3, ("ingest",)),
    ("export", "export", 1, ("cpm", "avis")),
]


@pytest.fixture(params=["sqlite", "postgresql"])
def sm(request, tmp_path):
    if request.param == "sqlite":
        yield session_factory(f"sqlite:///{tmp_path / 'ledger.db'}")
    else:
        with fresh_postgres() as url:
            yield session_factory(url)


class Recorder:
    """A sender that records messages (the broker itself is tested in test_service_farm)."""

    def __init__(self):
        self.sent: list[tuple[str, tuple, str, str]] = []
        self.lock = threading.Lock()

    def __call__(self, task, args, queue, task_id):
        with self.lock:
            self.sent.append((task, tuple(args), queue, task_id))


def new_job(sm, job_id="j1") -> str:
    with sm.begin() as s:
        if s.get(Asset, "a1") is None:
            s.add(
                Asset(
                    id="a1",
                    tenant="t",
                    sha256="0" * 64,
                    filename="x.usda",
                    kind="usda",
                    root_layer="x.usda",
                    size_bytes=1,
                    n_files=1,
                )
            )
    ledger.create_job(sm, job_id, "t", "a1", "{}")
    return job_id


def run(sm, job, stage, shard, worker="w:1", max_attempts=3):
    st = ledger.start_shard(sm, job, stage, shard, worker, max_attempts)
    assert st.action == "run"
    return ledger.finish_shard(sm, job, stage, shard, f"{stage}/{shard}", 0.01)


def test_plan_fan_out_fan_in(sm):
    job = new_job(sm)
    sends = ledger.record_plan(sm, job, PLAN, [("btf", "off")])
    assert [(s.args[1], s.args[2]) for s in sends] == [("ingest", 0)]
    # planning twice is harmless: nothing new to send
    assert ledger.record_plan(sm, job, PLAN, []) == []
    sends = run(sm, job, "ingest", 0)
    assert sorted((s.args[1], s.args[2]) for s in sends) == sorted(
        [("cpm", k) for k in range(6)] + [("avis", k) for k in range(3)]
    )
    assert {s.queue for s in sends} == {"cpm", "avis"}
    for k in range(6):
        assert run(sm, job, "cpm", k) == []  # export still waits for avis
    out = []
    for k in range(3):
        out += run(sm, job, "avis", k)
    assert [(s.args[1], s.args[2]) for s in out] == [("export", 0)]
    assert run(sm, job, "export", 0) == []
    secs = ledger.stage_seconds(sm, job)
    assert set(secs) == {"ingest", "cpm", "avis", "export"} and min(secs.values()) >= 0
    with sm() as s:
        assert s.get(Job, job).state == "succeeded"
        assert all(r.completions == 1 for r in s.scalars(select(Shard)))


def test_finish_twice_counts_once(sm):
    job = new_job(sm)
    ledger.record_plan(sm, job, PLAN, [])
    run(sm, job, "ingest", 0)
    run(sm, job, "cpm", 0)
    assert ledger.finish_shard(sm, job, "cpm", 0, "cpm/0", 0.01) == []
    assert ledger.start_shard(sm, job, "cpm", 0, "w:2", 3).action == "done"
    with sm() as s:
        row = s.scalar(select(Shard).where(Shard.stage == "cpm", Shard.shard == 0))
        assert (row.state, row.completions, row.attempts) == ("done", 1, 1)


@pytest.mark.timeout(60)
def test_concurrent_last_shards_promote_once(sm):
    """Eight threads finish the eight shards of a stage at once (a barrier lines them up);
    the next stage must be queued exactly once. Repeated to give the race chances."""
    plan = [("a", "cpm", 8, ()), ("b", "export", 1, ("a",))]
    for rep in range(4):
        job = new_job(sm, f"race{rep}")
        ledger.record_plan(sm, job, plan, [])
        for k in range(8):
            assert ledger.start_shard(sm, job, "a", k, f"w:{k}", 3).action == "run"
        barrier = threading.Barrier(8)
        results: list[list] = [None] * 8  # type: ignore[list-item]

        def finish(k, job=job, barrier=barrier, results=results):
            barrier.wait()
            results[k] = ledger.finish_shard(sm, job, "a", k, f"a/{k}", 0.01)

        threads = [threading.Thread(target=finish, args=(k,)) for k in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        promoted = [s for r in results for s in r]
        assert [(s.args[1], s.args[2]) for s in promoted] == [("b", 0)], rep


def test_redelivery_cap(sm):
    job = new_job(sm)
    ledger.record_plan(sm, job, PLAN, [])
    # three deliveries that each die mid-shard (the row stays "running")
    assert ledger.start_shard(sm, job, "ingest", 0, "w:1", 3).action == "run"
    assert ledger.start_shard(sm, job, "ingest", 0, "w:2", 3).action == "run"  # lost 1
    assert ledger.start_shard(sm, job, "ingest", 0, "w:3", 3).action == "run"  # lost 2
    res = ledger.start_shard(sm, job, "ingest", 0, "w:4", 3)  # lost 3: cap reached
    assert res.action == "exceeded"
    with sm() as s:
        j = s.get(Job, job)
        assert j.state == "failed"
        assert "ingest/0" in j.error and "max_attempts=3" in j.error


def test_sweep_resends_after_broker_restart_and_lease(sm):
    job = new_job(sm)
    rec = Recorder()
    ledger.dispatch(sm, [ledger.Send(ledger.PLAN_JOB_TASK, (job,), "ingest", None, job)], rec, "r1")
    assert ledger.sweep(sm, "r1", timedelta(seconds=60)) == []
    # a broker restart loses the plan message: re-sent
    assert [s.task for s in ledger.sweep(sm, "r2", timedelta(seconds=60))] == [ledger.PLAN_JOB_TASK]
    sends = ledger.record_plan(sm, job, PLAN, [])
    ledger.dispatch(sm, sends, rec, "r2")
    assert ledger.sweep(sm, "r2", timedelta(seconds=60)) == []
    lost = ledger.sweep(sm, "r3", timedelta(seconds=60))
    assert [(s.args[1], s.args[2]) for s in lost] == [("ingest", 0)]
    # two sweepers racing on the same rows: the task-id claim lets one send
    rec2 = Recorder()
    n1 = ledger.dispatch(sm, lost, rec2, "r3")
    n2 = ledger.dispatch(sm, lost, rec2, "r3")
    assert (n1, n2, len(rec2.sent)) == (1, 0, 1)
    # a running shard past its lease goes back to the queue
    assert ledger.start_shard(sm, job, "ingest", 0, "w:1", 3).action == "run"
    assert ledger.sweep(sm, "r3", timedelta(seconds=60)) == []
    later = utcnow() + timedelta(seconds=120)
    again = ledger.sweep(sm, "r3", timedelta(seconds=60), now=later)
    assert [(s.args[1], s.args[2]) for s in again] == [("ingest", 0)]


def test_send_failure_leaves_rows_for_the_sweeper(sm):
    job = new_job(sm)
    sends = ledger.record_plan(sm, job, PLAN, [])

    def down(*_a):
        raise ConnectionError("broker down")

    with pytest.raises(ConnectionError):
        ledger.dispatch(sm, sends, down, None)
    again = ledger.sweep(sm, "r1", timedelta(seconds=60))
    assert [(s.args[1], s.args[2]) for s in again] == [("ingest", 0)]
    rec = Recorder()
    assert ledger.dispatch(sm, again, rec, "r1") == 1


def test_cancel_keeps_state_and_stops_work(sm):
    job = new_job(sm)
    rec = Recorder()
    ledger.dispatch(sm, ledger.record_plan(sm, job, PLAN, []), rec, "r1")
    assert ledger.start_shard(sm, job, "ingest", 0, "w:1", 3).action == "run"
    ids = ledger.cancel_job(sm, job)
    assert ids == [rec.sent[0][3]]
    assert ledger.cancel_job(sm, job) == []  # already cancelled
    assert ledger.finish_shard(sm, job, "ingest", 0, "k", 0.1) == []
    assert ledger.start_shard(sm, job, "ingest", 0, "w:2", 3).action == "inactive"
    with sm() as s:
        assert s.get(Job, job).state == "cancelled"
        assert {r.state for r in s.scalars(select(Shard))} == {"cancelled"}
