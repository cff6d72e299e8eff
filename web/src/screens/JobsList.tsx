// Jobs: this tenant's jobs, a page at a time (server-side paging and filters), with live
// state and progress from the tenant's events stream.
import { useEffect, useRef, useState } from "preact/hooks";
import { api, errorText, type JobState, type JobSummary } from "../api/client";
import { openEvents } from "../api/sse";
import {
  ErrorBox,
  fmtSeconds,
  fmtTime,
  ProgressBar,
  StateBadge,
  toDate,
} from "../components/common";

export const PAGE_SIZE = 50;
const STATES: JobState[] = ["queued", "running", "succeeded", "failed", "cancelled"];

export function JobsList() {
  const [jobs, setJobs] = useState<JobSummary[] | null>(null);
  const [count, setCount] = useState(0);
  const [page, setPage] = useState(0);
  const [state, setState] = useState<JobState | "">("");
  const [asset, setAsset] = useState("");
  const [error, setError] = useState<string | null>(null);
  const [reload, setReload] = useState(0);
  const pending = useRef<number | null>(null);

  useEffect(() => {
    let stale = false;
    (async () => {
      const { data, error: err, response } = await api.GET("/api/v1/jobs", {
        params: {
          query: {
            skip: page * PAGE_SIZE,
            limit: PAGE_SIZE,
            ...(state ? { state } : {}),
            ...(asset.trim() ? { asset_id: asset.trim() } : {}),
          },
        },
      });
      if (stale) return;
      if (err || !data) {
        setError(errorText(err, response.status));
        return;
      }
      setError(null);
      setJobs(data.data);
      setCount(data.count);
    })();
    return () => {
      stale = true;
    };
  }, [page, state, asset, reload]);

  // live: one stream of all of this tenant's job events (a browser holds at most six
  // connections per host, so not one per job); `ready` and every event re-read the page
  // (debounced), so state and progress follow the ledger without polling
  useEffect(
    () =>
      openEvents("/api/v1/events", {
        onMessage: () => {
          if (pending.current === null)
            pending.current = window.setTimeout(() => {
              pending.current = null;
              setReload((n) => n + 1);
            }, 300);
        },
      }),
    [],
  );
  useEffect(
    () => () => {
      if (pending.current !== null) clearTimeout(pending.current);
      pending.current = null;
    },
    [],
  );

  const pages = Math.max(1, Math.ceil(count / PAGE_SIZE));
  return (
    <section>
      <div class="section-head">
        <h2>Jobs</h2>
        <a class="btn primary" href="#/upload">
          New bake
        </a>
      </div>
      <div class="filters">
        <label>
          State{" "}
          <select
            data-testid="filter-state"
            value={state}
            onChange={(e) => {
              setPage(0);
              setState((e.target as HTMLSelectElement).value as JobState | "");
            }}
          >
            <option value="">all</option>
            {STATES.map((s) => (
              <option value={s}>{s}</option>
            ))}
          </select>
        </label>
        <label>
          Asset{" "}
          <input
            data-testid="filter-asset"
            placeholder="asset id"
            value={asset}
            onChange={(e) => {
              setPage(0);
              setAsset((e.target as HTMLInputElement).value);
            }}
          />
        </label>
        <span class="muted">
          {count} job{count === 1 ? "" : "s"}
        </span>
      </div>
      {error && <ErrorBox>{error}</ErrorBox>}
      {jobs === null ? (
        <p class="muted">Loading…</p>
      ) : jobs.length === 0 ? (
        <p class="muted" data-testid="no-jobs">
          No jobs yet. <a href="#/upload">Upload an asset</a> to start a bake.
        </p>
      ) : (
        <table class="table" data-testid="jobs-table">
          <thead>
            <tr>
              <th>Job</th>
              <th>Asset</th>
              <th>State</th>
              <th class="w-progress">Progress</th>
              <th>Created</th>
              <th>Took</th>
            </tr>
          </thead>
          <tbody>
            {jobs.map((j) => (
              <tr data-testid="job-row" data-job-id={j.id} data-state={j.state} key={j.id}>
                <td>
                  <a class="mono" href={`#/jobs/${j.id}`}>
                    {j.id.slice(0, 12)}
                  </a>
                </td>
                <td class="mono small">{j.asset_id.slice(0, 12)}</td>
                <td>
                  <StateBadge state={j.state} />
                  {j.error && <div class="error small clip" title={j.error}>{j.error}</div>}
                </td>
                <td>
                  <ProgressBar value={j.progress} state={j.state} />
                </td>
                <td class="small">{fmtTime(j.created_at)}</td>
                <td class="small">
                  {j.finished_at
                    ? fmtSeconds(
                        (toDate(j.finished_at).getTime() - toDate(j.created_at).getTime()) / 1000,
                      )
                    : "—"}
                </td>
              </tr>
            ))}
          </tbody>
        </table>
      )}
      {pages > 1 && (
        <div class="pager">
          <button class="btn" disabled={page === 0} onClick={() => setPage(page - 1)}>
            ‹ Newer
          </button>
          <span>
            page {page + 1} of {pages}
          </span>
          <button class="btn" disabled={page + 1 >= pages} onClick={() => setPage(page + 1)}>
            Older ›
          </button>
        </div>
      )}
    </section>
  );
}
