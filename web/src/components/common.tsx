// Small shared pieces: state badges, progress bars, times.
import type { ComponentChildren } from "preact";

export function StateBadge({ state }: { state: string }) {
  return (
    <span class={`badge state-${state}`} data-state={state}>
      {state}
    </span>
  );
}

export function ProgressBar({ value, state }: { value: number; state?: string }) {
  const pct = Math.round(Math.max(0, Math.min(1, value)) * 100);
  return (
    <div class={`progress state-${state ?? "running"}`} role="progressbar" aria-valuenow={pct} aria-valuemin={0} aria-valuemax={100}>
      <div class="progress-fill" style={{ width: `${pct}%` }} />
      <span class="progress-label">{pct}%</span>
    </div>
  );
}

/** The API's datetimes are UTC, written without an offset. */
export function toDate(iso: string): Date {
  return new Date(/[zZ]|[+-]\d\d:\d\d$/.test(iso) ? iso : `${iso}Z`);
}

export function fmtTime(iso: string | null | undefined): string {
  if (!iso) return "—";
  return toDate(iso).toISOString().replace("T", " ").slice(0, 19) + " UTC";
}

export function fmtSeconds(s: number | null | undefined): string {
  if (s === null || s === undefined) return "—";
  if (s < 1) return `${(s * 1000).toFixed(0)} ms`;
  if (s < 120) return `${s.toFixed(1)} s`;
  return `${(s / 60).toFixed(1)} min`;
}

export function ErrorBox({ children }: { children: ComponentChildren }) {
  return (
    <div class="error-box" role="alert">
      {children}
    </div>
  );
}

/** Prim paths (/World/Box) and file names (x.usda, tex/a.png) an error names. */
const NAMED = /(\/[A-Za-z_][\w]*(?:\/[\w.:]+)*|[\w./-]+\.(?:usda|usdc|usd|usdz|zip|png|exr|jpg|tx))/g;

/** An error message with the prims and files it names set off, so they can be copied. */
export function ErrorText({ text }: { text: string }) {
  const parts = text.split(NAMED);
  return (
    <span>
      {parts.map((p, i) =>
        i % 2 === 1 ? (
          <code class="named" data-testid="error-named">
            {p}
          </code>
        ) : (
          p
        ),
      )}
    </span>
  );
}
