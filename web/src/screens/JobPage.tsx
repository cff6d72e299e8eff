// One job: state, per-stage and per-shard progress (a grid of shards coloured by state),
// timings, errors, settings, cancel and download; tabs for the previews and the plot.
import { useEffect, useRef, useState } from "preact/hooks";
import { api, errorText, fetchBlob, TERMINAL, type JobPublic } from "../api/client";
import { openEvents } from "../api/sse";
import { ErrorBox, ErrorText, fmtSeconds, fmtTime, ProgressBar, StateBadge } from "../components/common";
import { groupedProps, isDefault, useSettingsSchema } from "../components/SettingsForm";
import { ShardGrid } from "../components/ShardGrid";
import { Previews } from "./Previews";
import { Inspector } from "./Inspector";
import { SpeedErrorPlot } from "./SpeedErrorPlot";
import { Viewer } from "./Viewer";

export function JobPage({ id, tab }: { id: string; tab: string }) {
  const [job, setJob] = useState<JobPublic | null>(null);
  const [error, setError] = useState<string | null>(null);
  const [notice, setNotice] = useState<string | null>(null);
  const [busy, setBusy] = useState(false);
  const timer = useRef<number | null>(null);

  async function load(): Promise<JobPublic | null> {
    const { data, error: err, response } = await api.GET("/api/v1/jobs/{job_id}", {
      params: { path: { job_id: id } },
    });
    if (err || !data) {
      setError(errorText(err, response.status));
      return null;
    }
    setError(null);
    setJob(data);
    return data;
  }

  useEffect(() => {
    setJob(null);
    let close = () => {};
    let alive = true;
    (async () => {
      const first = await load();
      if (!alive || !first || TERMINAL.has(first.state)) return;
      // live: the job's events; each (debounced) re-reads the job, which the API caches per
      // event sequence number
      let finished = false;
      close = openEvents(`/api/v1/jobs/${id}/events`, {
        done: () => finished,
        onMessage: (m) => {
          try {
            const ev = JSON.parse(m.data);
            if (ev.kind === "job" && TERMINAL.has(ev.data?.state)) finished = true;
          } catch {
            /* a malformed event changes nothing */
          }
          if (timer.current === null)
            timer.current = window.setTimeout(() => {
              timer.current = null;
              void load();
            }, 250);
        },
      });
    })();
    return () => {
      alive = false;
      close();
      if (timer.current !== null) clearTimeout(timer.current);
      timer.current = null;
    };
  }, [id]);

  async function cancel() {
    setBusy(true);
    const { data, error: err, response } = await api.DELETE("/api/v1/jobs/{job_id}", {
      params: { path: { job_id: id } },
    });
    setBusy(false);
    if (err || !data) setNotice(errorText(err, response.status));
    else {
      setJob(data);
      setNotice("Cancelled.");
    }
  }

  async function download() {
    setBusy(true);
    try {
      const blob = await fetchBlob(`/api/v1/jobs/${encodeURIComponent(id)}/result`);
      const url = URL.createObjectURL(blob);
      const a = document.createElement("a");
      a.href = url;
      a.download = `${id}.zip`;
      a.click();
      setTimeout(() => URL.revokeObjectURL(url), 10_000);
      setNotice(`Downloaded ${id}.zip (${(blob.size / 1024).toFixed(0)} KiB).`);
    } catch (e) {
      setNotice(String((e as Error).message ?? e));
    } finally {
      setBusy(false);
    }
  }

  if (error)
    return (
      <section>
        <h2>
          Job <span class="mono">{id.slice(0, 12)}</span>
        </h2>
        <ErrorBox>{error}</ErrorBox>
        <a href="#/jobs">‹ All jobs</a>
      </section>
    );
  if (!job) return <p class="muted">Loading…</p>;
  const terminal = TERMINAL.has(job.state);
  const hasPreviews = (job.previews ?? []).length > 0;
  const tabLink = (name: string, label: string, enabled = true) =>
    enabled ? (
      <a class={tab === name ? "tab active" : "tab"} href={`#/jobs/${id}/${name}`} data-testid={`tab-${name}`}>
        {label}
      </a>
    ) : (
      <span class="tab disabled" title="not available for this job yet">
        {label}
      </span>
    );
  const shardErrors = job.stages.flatMap((st) =>
    (st.shards ?? []).filter((s) => s.error).map((s) => ({ stage: st.name, shard: s.shard, error: s.error! })),
  );

  return (
    <section data-testid="job-page" data-job-id={job.id} data-state={job.state}>
      <div class="section-head">
        <h2>
          Job <span class="mono">{job.id.slice(0, 12)}</span> <StateBadge state={job.state} />
        </h2>
        <div class="actions">
          <button class="btn danger" data-testid="cancel" disabled={terminal || busy} onClick={cancel}>
            Cancel
          </button>
          <button
            class="btn primary"
            data-testid="download"
            disabled={job.state !== "succeeded" || busy}
            onClick={download}
          >
            Download result
          </button>
        </div>
      </div>
      {notice && <p class="notice" data-testid="notice">{notice}</p>}
      <ProgressBar value={job.progress} state={job.state} />
      <nav class="tabs">
        {tabLink("overview", "Overview")}
        {tabLink("previews", "Previews", hasPreviews)}
        {tabLink("plot", "Speed vs error", hasPreviews)}
        {tabLink("inspector", "Texel inspector", job.state === "succeeded")}
        {tabLink("viewer", "3-D viewer", job.state === "succeeded")}
      </nav>
      {tab === "previews" && hasPreviews ? (
        <Previews job={job} />
      ) : tab === "plot" && hasPreviews ? (
        <SpeedErrorPlot job={job} />
      ) : tab === "inspector" && job.state === "succeeded" ? (
        <Inspector job={job} />
      ) : tab === "viewer" && job.state === "succeeded" ? (
        <Viewer job={job} />
      ) : (
        <div class="job-grid">
          <div class="card">
            <h3>Timings</h3>
            <dl class="kv">
              <dt>Asset</dt>
              <dd class="mono">{job.asset_id}</dd>
              <dt>Created</dt>
              <dd>{fmtTime(job.created_at)}</dd>
              <dt>Started</dt>
              <dd>{fmtTime(job.started_at)}</dd>
              <dt>Finished</dt>
              <dd>{fmtTime(job.finished_at)}</dd>
              <dt>Wall time</dt>
              <dd>{fmtSeconds(job.seconds)}</dd>
            </dl>
            {job.error && (
              <ErrorBox>
                <strong>Error:</strong> <ErrorText text={job.error} />
              </ErrorBox>
            )}
            {shardErrors.map((e) => (
              <ErrorBox>
                <strong>
                  {e.stage}/{e.shard}:
                </strong>{" "}
                <ErrorText text={e.error} />
              </ErrorBox>
            ))}
            {(job.skipped ?? []).length > 0 && (
              <>
                <h4>Skipped stages</h4>
                <ul class="small">
                  {(job.skipped ?? []).map((s) => (
                    <li>
                      <strong>{s.stage}</strong>: {s.reason}
                    </li>
                  ))}
                </ul>
              </>
            )}
          </div>
          <JobSettings settings={job.settings as Record<string, unknown>} />
          <div class="card stages">
            <h3>Stages</h3>
            {job.stages.length === 0 && <p class="muted">Not planned yet (waiting for the ingest worker).</p>}
            {job.stages.length > 0 && (
            <table class="table compact" data-testid="stages">
              <thead>
                <tr>
                  <th>Stage</th>
                  <th>Queue</th>
                  <th>State</th>
                  <th>Shards</th>
                  <th>Time</th>
                </tr>
              </thead>
              <tbody>
                {job.stages.map((st) => (
                  <tr data-testid="stage-row" data-stage={st.name} data-state={st.state}>
                    <td>{st.name}</td>
                    <td class="small">{st.queue}</td>
                    <td>
                      <StateBadge state={st.state} />
                    </td>
                    <td>
                      <ShardGrid stage={st} />
                      <span class="small muted">
                        {st.n_done}/{st.n_shards}
                      </span>
                    </td>
                    <td class="small">{fmtSeconds(st.seconds)}</td>
                  </tr>
                ))}
              </tbody>
            </table>
            )}
          </div>
        </div>
      )}
    </section>
  );
}


/** The job's settings: the fields that differ from the defaults first, then the rest by group
 * (folded away). */
function JobSettings({ settings }: { settings: Record<string, unknown> }) {
  const { schema } = useSettingsSchema();
  const props = schema?.properties ?? {};
  const changed = Object.entries(settings).filter(([k, v]) => !isDefault(props[k], v));
  const kv = (entries: [string, unknown][]) => (
    <dl class="kv small">
      {entries.map(([k, v]) => (
        <>
          <dt>{k}</dt>
          <dd class="mono">{Array.isArray(v) ? v.join(", ") : String(v)}</dd>
        </>
      ))}
    </dl>
  );
  return (
    <div class="card settings" data-testid="settings">
      <h3>Settings</h3>
      <h4>Changed from the defaults</h4>
      <div data-testid="settings-changed">
        {changed.length > 0 ? kv(changed) : <p class="muted small">none: the default bake</p>}
      </div>
      {schema && (
        <details data-testid="settings-defaults">
          <summary class="small">the other {Object.keys(settings).length - changed.length} at their defaults, by group</summary>
          {groupedProps(schema).map(([group, fields]) => {
            const rest = fields
              .filter(([k]) => k in settings && isDefault(props[k], settings[k]))
              .map(([k]): [string, unknown] => [k, settings[k]]);
            return rest.length > 0 ? (
              <div data-group={group}>
                <h4>{group}</h4>
                {kv(rest)}
              </div>
            ) : null;
          })}
        </details>
      )}
    </div>
  );
}
