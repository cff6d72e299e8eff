// The farm: workers and their queues, queue lengths, the shards running now; live from the
// farm events stream (a snapshot every 2 s).
import { useEffect, useState } from "preact/hooks";
import type { FarmPublic } from "../api/client";
import { openEvents } from "../api/sse";
import { ErrorBox, fmtTime } from "../components/common";

export function Farm() {
  const [farm, setFarm] = useState<FarmPublic | null>(null);
  const [error, setError] = useState<string | null>(null);
  useEffect(
    () =>
      openEvents("/api/v1/farm/events", {
        onMessage: (m) => {
          setError(null);
          setFarm(JSON.parse(m.data));
        },
        onError: (e) => setError(String((e as Error).message ?? e)),
      }),
    [],
  );
  if (error && !farm) return <ErrorBox>{error}</ErrorBox>;
  if (!farm) return <p class="muted">Connecting to the farm…</p>;
  const maxLen = Math.max(1, ...farm.queues.map((q) => (q.length ?? 0) + q.running));
  return (
    <section data-testid="farm">
      <div class="section-head">
        <h2>Farm</h2>
        <span class="muted small">
          {farm.broker ? "broker up" : "broker DOWN"} · updated {fmtTime(farm.at)}
        </span>
      </div>
      <div class="job-grid">
        <div class="card">
          <h3>Workers ({farm.workers.length})</h3>
          {farm.workers.length === 0 ? (
            <p class="muted">No worker answered Celery's inspection.</p>
          ) : (
            <table class="table compact workers" data-testid="workers">
              <thead>
                <tr>
                  <th>Worker</th>
                  <th>Queues</th>
                  <th>Active</th>
                  <th>Processes</th>
                </tr>
              </thead>
              <tbody>
                {farm.workers.map((w) => (
                  <tr data-testid="worker-row">
                    <td class="mono">{w.name}</td>
                    <td>{w.queues.join(", ")}</td>
                    <td>{w.active}</td>
                    <td>{w.concurrency ?? "—"}</td>
                  </tr>
                ))}
              </tbody>
            </table>
          )}
        </div>
        <div class="card">
          <h3>Queues</h3>
          <table class="table compact" data-testid="queues">
            <thead>
              <tr>
                <th>Queue</th>
                <th>Waiting (broker)</th>
                <th>Queued (ledger)</th>
                <th>Running</th>
                <th class="w-progress" />
              </tr>
            </thead>
            <tbody>
              {farm.queues.map((q) => (
                <tr data-testid="queue-row" data-queue={q.name}>
                  <td>{q.name}</td>
                  <td>{q.length ?? "?"}</td>
                  <td>{q.queued}</td>
                  <td>{q.running}</td>
                  <td>
                    <div class="qbar">
                      <span class="qbar-run" style={{ width: `${(q.running / maxLen) * 100}%` }} />
                      <span class="qbar-wait" style={{ width: `${((q.length ?? 0) / maxLen) * 100}%` }} />
                    </div>
                  </td>
                </tr>
              ))}
            </tbody>
          </table>
        </div>
        <div class="card wide">
          <h3>Running shards ({farm.current.length})</h3>
          {farm.current.length === 0 ? (
            <p class="muted">Nothing is running.</p>
          ) : (
            <table class="table compact" data-testid="current-shards">
              <thead>
                <tr>
                  <th>Job</th>
                  <th>Stage</th>
                  <th>Shard</th>
                  <th>Worker</th>
                  <th>Started</th>
                  <th>Attempts</th>
                </tr>
              </thead>
              <tbody>
                {farm.current.map((c) => (
                  <tr>
                    <td class="mono">
                      {c.job_id ? <a href={`#/jobs/${c.job_id}`}>{c.job_id.slice(0, 12)}</a> : <span class="muted">another tenant</span>}
                    </td>
                    <td>{c.stage}</td>
                    <td>{c.shard}</td>
                    <td class="mono small">{c.worker ?? "—"}</td>
                    <td class="small">{fmtTime(c.started_at)}</td>
                    <td>{c.attempts}</td>
                  </tr>
                ))}
              </tbody>
            </table>
          )}
        </div>
      </div>
    </section>
  );
}
