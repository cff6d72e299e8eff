"""The shard ledger's transitions on SQLite and PostgreSQL: fan-out/fan-in, exactly-once
promotion under concurrent finishes, the redelivery cap, the sweeper, cancel."""

from __future__ import annotations

import threading
from datetime import timedelta

import pytest
from sqlalchemy import select

from farm import ledger
from farm.db import Asset, Job, Shard, session_factory, utcnow
from tests.helpers.service import fresh_postgres

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


def test_expired_leases_count_as_lost_and_fail_at_the_cap(sm):
    """A shard whose heartbeats stopped (its worker died, or it passed its time limit) is lost
    each time the sweeper re-queues it: without the count a shard that hangs on every delivery
    would be re-queued for ever. The failure names the last error recorded on the row."""
    job = new_job(sm)
    ledger.dispatch(sm, ledger.record_plan(sm, job, PLAN, []), Recorder(), "r1")
    lease = timedelta(seconds=60)
    for k in (1, 2):
        assert ledger.start_shard(sm, job, "ingest", 0, f"w:{k}", 3).action == "run"
        assert ledger.note_time_limit(sm, job, "ingest", 0, f"w:{k}", 5.0)
        assert not ledger.note_time_limit(sm, job, "ingest", 0, "w:other", 5.0)  # not its shard
        later = utcnow() + timedelta(seconds=120)
        again = ledger.sweep(sm, "r1", lease, now=later, max_attempts=3)
        assert [(x.args[1], x.args[2]) for x in again] == [("ingest", 0)]
        ledger.dispatch(sm, again, Recorder(), "r1")
        with sm() as s:
            row = s.scalar(select(Shard).where(Shard.job_id == job, Shard.stage == "ingest"))
            assert (row.state, row.lost) == ("queued", k)
    assert ledger.start_shard(sm, job, "ingest", 0, "w:3", 3).action == "run"
    ledger.note_time_limit(sm, job, "ingest", 0, "w:3", 5.0)
    assert ledger.sweep(sm, "r1", lease, now=utcnow() + timedelta(seconds=120),
                        max_attempts=3) == []
    with sm() as s:
        j = s.get(Job, job)
        assert j.state == "failed"
        assert "lost 3 times" in j.error and "exceeded the shard time limit of 5 s" in j.error


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


# ---------------------------------------------------------------- admission (issue 16, item 2)


def new_tenant_job(sm, job_id, tenant, priority, plan, policy):
    """A planned job of `tenant` at `priority`; returns the sends its planning admitted."""
    with sm.begin() as s:
        if s.get(Asset, "a1") is None:
            s.add(Asset(id="a1", tenant="t", sha256="0" * 64, filename="x.usda", kind="usda",
                        root_layer="x.usda", size_bytes=1, n_files=1))
    ledger.create_job(sm, job_id, tenant, "a1", "{}", priority=priority)
    return ledger.record_plan(sm, job_id, plan, [], policy)


class Farm:
    """A broker and `workers` workers simulated over the real ledger: the broker is FIFO (as a
    Redis list), a worker takes the oldest message, starts and finishes its shard; what the
    ledger admits goes to the back of the broker. Records the order shards start in and the
    most shards any tenant held at once."""

    def __init__(self, sm, policy, tenants):
        self.sm, self.policy, self.tenants = sm, policy, tenants
        self.broker: list = []
        self.started: list[tuple[str, str, int]] = []
        self.running: list = []
        self.peak: dict[str, int] = {}

    def send(self, sends):
        self.broker += list(sends)

    def step(self, workers=1):
        """Start up to `workers` shards, then finish the oldest running one."""
        while self.broker and len(self.running) < workers:
            m = self.broker.pop(0)
            job, stage, k = m.args
            r = ledger.start_shard(self.sm, job, stage, k, "w:1", 3, self.policy)
            assert r.action == "run", (m.args, r)
            self.send(r.sends)
            self.started.append((job, stage, k))
            self.running.append(m.args)
            held: dict[str, int] = {}
            for j, _s, _k in self.running:
                held[self.tenants[j]] = held.get(self.tenants[j], 0) + 1
            for t, n in held.items():
                self.peak[t] = max(self.peak.get(t, 0), n)
        if not self.running:
            return False
        job, stage, k = self.running.pop(0)
        self.send(ledger.finish_shard(self.sm, job, stage, k, f"{stage}/{k}", 0.01, self.policy))
        return True

    def drain(self, workers=1):
        while self.step(workers):
            pass


def test_priority_orders_the_queue(sm):
    """A later job of higher priority overtakes an earlier one's waiting shards: with a
    backlog of one message the broker's FIFO order no longer decides."""
    policy = ledger.Policy(queue_backlog=1)
    plan = [("s", "cpm", 3, ())]
    farm = Farm(sm, policy, {"lo": "t1", "hi": "t2"})
    farm.send(new_tenant_job(sm, "lo", "t1", 10, plan, policy))
    farm.send(new_tenant_job(sm, "hi", "t2", 90, plan, policy))
    assert [m.args[0] for m in farm.broker] == ["lo"]  # the backlog is full
    farm.drain()
    assert [j for j, _s, _k in farm.started] == ["lo", "hi", "hi", "hi", "lo", "lo"]
    # without a backlog limit the broker's FIFO decides: the earlier job first
    fifo = Farm(sm, ledger.NO_LIMITS, {"lo2": "t1", "hi2": "t2"})
    fifo.send(new_tenant_job(sm, "lo2", "t1", 10, plan, ledger.NO_LIMITS))
    fifo.send(new_tenant_job(sm, "hi2", "t2", 90, plan, ledger.NO_LIMITS))
    fifo.drain()
    assert [j for j, _s, _k in fifo.started] == ["lo2"] * 3 + ["hi2"] * 3


def test_tenant_limit_and_equal_priority_alternate(sm):
    """A tenant never holds more shards than its limit, whatever the worker count; another
    tenant's single later job starts as soon as a slot frees, not after the batch."""
    policy = ledger.Policy(queue_backlog=0, tenant_max_running=2)
    plan = [("a", "cpm", 4, ()), ("b", "export", 1, ("a",))]
    tenants = {f"batch{i}": "big" for i in range(3)} | {"single": "small"}
    farm = Farm(sm, policy, tenants)
    for i in range(3):
        farm.send(new_tenant_job(sm, f"batch{i}", "big", 50, plan, policy))
    assert len(farm.broker) == 2  # the limit, not the 12 ready shards
    farm.send(new_tenant_job(sm, "single", "small", 50, plan, policy))
    farm.drain(workers=4)
    assert farm.peak == {"big": 2, "small": 2}
    first = [k for k, (j, _s, _k) in enumerate(farm.started) if j == "single"][0]
    assert first <= 2, farm.started  # started with the batch's first shards
    with sm() as s:
        assert {j.state for j in s.scalars(select(Job))} == {"succeeded"}
    # at equal priority and no limit, the tenant holding fewer shards goes first
    p2 = ledger.Policy(queue_backlog=1)
    rr = Farm(sm, p2, {"bulk": "big", "one": "small"})
    rr.send(new_tenant_job(sm, "bulk", "big", 50, [("a", "cpm", 5, ())], p2))
    rr.send(new_tenant_job(sm, "one", "small", 50, [("a", "cpm", 1, ())], p2))
    rr.drain()
    assert [j for j, _s, _k in rr.started][:2] == ["bulk", "one"]


def test_sweep_admits_what_a_failed_job_freed(sm):
    """Slots held by a job that fails are given to ready shards by the sweeper."""
    policy = ledger.Policy(queue_backlog=0, tenant_max_running=1)
    plan = [("a", "cpm", 2, ())]
    first = new_tenant_job(sm, "f1", "t", 50, plan, policy)
    assert len(first) == 1 and new_tenant_job(sm, "f2", "t", 50, plan, policy) == []
    ledger.fail_job(sm, "f1", "boom")
    again = ledger.sweep(sm, "r1", timedelta(seconds=60), policy=policy)
    assert [(s.args[0], s.args[2]) for s in again] == [("f2", 0)]


def test_priority_spans_the_queues_of_a_group(sm):
    """Workers that serve several queues take from whichever has a message, so the backlog and
    the priority order are per queue group: with cpm and export in one group, a high-priority
    job's second cpm shard goes before a low-priority job's export; with a backlog per queue
    the export slips in between."""
    def order(policy, tag):
        farm = Farm(sm, policy, {f"lo{tag}": "t1", f"hi{tag}": "t2"})
        farm.send(new_tenant_job(sm, f"lo{tag}", "t1", 10,
                                 [("a", "cpm", 1, ()), ("b", "export", 1, ("a",))], policy))
        farm.send(new_tenant_job(sm, f"hi{tag}", "t2", 90,
                                 [("a", "cpm", 2, ()), ("b", "export", 1, ("a",))], policy))
        farm.drain()
        return [f"{j[:2]} {st}{k}" for j, st, k in farm.started]

    grouped = ledger.Policy(queue_backlog=1, groups=(("all", ("cpm", "export")),))
    assert order(grouped, "g") == ["lo a0", "hi a0", "hi a1", "lo b0", "hi b0"]
    assert order(ledger.Policy(queue_backlog=1), "q") == [
        "lo a0", "hi a0", "lo b0", "hi a1", "hi b0"]


def test_a_held_shard_is_not_run_twice_and_a_dead_holder_is_taken_over_at_once(sm):
    """A second delivery of a running shard (Celery's redelivery, a sweep of a lease that
    expired in a busy moment) runs it only when its holder is gone: a live process of this host
    holds it ("held"), a dead one (a killed pool child, a zombie) is taken over at once, and a
    holder on another host holds it while its heartbeats are within the lease."""
    import os
    import socket
    import subprocess
    import sys
    import time

    job = new_job(sm)
    ledger.dispatch(sm, ledger.record_plan(sm, job, PLAN, []), Recorder(), "r1")
    lease = timedelta(seconds=3)
    host = socket.gethostname()
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        alive = f"{host}:{child.pid}"
        assert ledger.holder_alive(alive) is True
        assert ledger.start_shard(sm, job, "ingest", 0, alive, 3, lease=lease).action == "run"
        me = f"{host}:{os.getpid()}"
        # its holder lives: held, however old its heartbeat (this host sees the process)
        assert ledger.start_shard(sm, job, "ingest", 0, me, 3, lease=lease).action == "held"
        assert ledger.start_shard(sm, job, "ingest", 0, me, 3, lease=timedelta(0)).action \
            == "held"
        child.kill()  # not reaped yet: a zombie, dead to the ledger
        deadline = time.monotonic() + 10
        while b") Z " not in open(f"/proc/{child.pid}/stat", "rb").read():
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert ledger.holder_alive(alive) is False
        child.wait()
        assert ledger.holder_alive(alive) is False
        res = ledger.start_shard(sm, job, "ingest", 0, me, 3, lease=lease)
        assert (res.action, res.attempts) == ("run", 2)  # at once, within the lease
    finally:
        child.kill()
        child.wait()
    with sm() as s:
        row = s.scalar(select(Shard).where(Shard.job_id == job, Shard.stage == "ingest"))
        assert (row.state, row.worker, row.lost) == ("running", me, 1)
    # another host's holder: its heartbeats decide
    other = "another-host.invalid:12345"
    assert ledger.holder_alive(other) is None
    ledger.finish_shard(sm, job, "ingest", 0, "ingest/0", 0.01)
    assert ledger.start_shard(sm, job, "cpm", 0, other, 3, lease=lease).action == "run"
    assert ledger.heartbeat(sm, job, "cpm", 0, other)
    assert ledger.start_shard(sm, job, "cpm", 0, me, 3, lease=lease).action == "held"
    with sm.begin() as s:  # its last beat 4 s ago: past the 3 s lease
        s.execute(Shard.__table__.update().where(
            Shard.job_id == job, Shard.stage == "cpm", Shard.shard == 0).values(
            heartbeat_at=utcnow() - timedelta(seconds=4)))
    assert ledger.start_shard(sm, job, "cpm", 0, me, 3, lease=lease).action == "run"

