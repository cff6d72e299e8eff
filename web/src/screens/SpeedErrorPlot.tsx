// Speed against error, drawn (SVG) from the job's render_report.json: every rendered entry of
// the sweep, x = seconds (log), y = object PSNR in dB; hover shows mode, spp, seconds, dB.
import { useEffect, useState } from "preact/hooks";
import { fetchBlob, previewUrl, type JobPublic } from "../api/client";
import { ErrorBox } from "../components/common";

export interface SweepEntry {
  mode: string;
  spp: number;
  seconds: number;
  psnr_db_object?: number | string;
  delta_e_mean?: number | string;
  flip_mean_object?: number | string;
  [k: string]: unknown;
}

interface ReportView {
  sweep?: SweepEntry[];
  reference?: { spp: number; seconds: number };
  width?: number;
  height?: number;
}

export const MODE_COLOURS: Record<string, string> = {
  gt: "#4e79a7",
  cpm: "#e15759",
  normalmap: "#59a14f",
  "equal-time": "#f28e2b",
  btf: "#b07aa1",
};

const METRICS: Record<string, { label: string; better: "higher" | "lower" }> = {
  psnr_db_object: { label: "PSNR over the object (dB)", better: "higher" },
  delta_e_mean: { label: "mean ΔE*ab", better: "lower" },
  flip_mean_object: { label: "FLIP over the object", better: "lower" },
};

const W = 640;
const H = 380;
const M = { l: 64, r: 16, t: 16, b: 48 };

function num(v: unknown): number | null {
  return typeof v === "number" && Number.isFinite(v) ? v : null;
}

/** Nice ticks of a log axis (1-2-5 per decade) between lo and hi. */
export function logTicks(lo: number, hi: number): number[] {
  const out: number[] = [];
  for (let e = Math.floor(Math.log10(lo)); e <= Math.ceil(Math.log10(hi)); e++)
    for (const m of [1, 2, 5]) {
      const v = m * 10 ** e;
      if (v >= lo && v <= hi) out.push(v);
    }
  return out;
}

export function linTicks(lo: number, hi: number, n = 6): number[] {
  const step0 = (hi - lo) / n;
  const mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map((k) => k * mag).find((s) => s >= step0) ?? step0;
  const out: number[] = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(+v.toFixed(10));
  return out;
}

export function SpeedErrorPlot({ job }: { job: JobPublic }) {
  const [report, setReport] = useState<(ReportView & { far?: ReportView }) | null>(null);
  const [error, setError] = useState<string | null>(null);
  const [viewName, setViewName] = useState<"near" | "far">("near");
  const [metric, setMetric] = useState("psnr_db_object");
  const [hover, setHover] = useState<SweepEntry | null>(null);
  const [at, setAt] = useState<{ x: number; y: number }>({ x: 0, y: 0 });

  useEffect(() => {
    (async () => {
      try {
        const blob = await fetchBlob(previewUrl(job.id, "render_report.json"));
        setReport(JSON.parse(await blob.text()));
      } catch (e) {
        setError((e as Error).message);
      }
    })();
  }, [job.id]);

  if (error) return <ErrorBox>render_report.json: {error}</ErrorBox>;
  if (!report) return <p class="muted">Loading the render report…</p>;
  const view = viewName === "far" && report.far ? report.far : report;
  const pts = (view.sweep ?? [])
    .map((e) => ({ e, x: num(e.seconds), y: num(e[metric]) }))
    .filter((p): p is { e: SweepEntry; x: number; y: number } => p.x !== null && p.x > 0 && p.y !== null);
  if (pts.length === 0) return <ErrorBox>The render report has no sweep entries with {metric}.</ErrorBox>;
  const xs = pts.map((p) => p.x);
  const ys = pts.map((p) => p.y);
  const x0 = Math.min(...xs) / 1.5;
  const x1 = Math.max(...xs) * 1.5;
  const pad = Math.max(0.5, (Math.max(...ys) - Math.min(...ys)) * 0.1);
  const y0 = Math.min(...ys) - pad;
  const y1 = Math.max(...ys) + pad;
  const sx = (x: number) => M.l + ((Math.log(x) - Math.log(x0)) / (Math.log(x1) - Math.log(x0))) * (W - M.l - M.r);
  const sy = (y: number) => H - M.b - ((y - y0) / (y1 - y0)) * (H - M.t - M.b);
  const modes = [...new Set(pts.map((p) => p.e.mode))];
  const lines = modes.map((m) => {
    const ps = pts.filter((p) => p.e.mode === m).sort((a, b) => a.x - b.x);
    return { m, d: ps.map((p, i) => `${i ? "L" : "M"}${sx(p.x).toFixed(1)},${sy(p.y).toFixed(1)}`).join(" ") };
  });
  const colour = (m: string) => MODE_COLOURS[m] ?? "#888";
  return (
    <div class="plot" data-testid="speed-error-plot">
      <div class="filters">
        <label>
          View{" "}
          <select value={viewName} onChange={(e) => setViewName((e.target as HTMLSelectElement).value as "near" | "far")}>
            <option value="near">near</option>
            {report.far && <option value="far">far</option>}
          </select>
        </label>
        <label>
          Error{" "}
          <select value={metric} onChange={(e) => setMetric((e.target as HTMLSelectElement).value)}>
            {Object.entries(METRICS).map(([k, v]) => (
              <option value={k}>{v.label}</option>
            ))}
          </select>
        </label>
        <span class="muted small">
          {METRICS[metric].better} is better · reference: gt at {view.reference?.spp} spp
          {view.width ? ` · ${view.width}×${view.height} px` : ""}
        </span>
      </div>
      <div class="plot-wrap">
        <div class="plot-area">
        <svg viewBox={`0 0 ${W} ${H}`} width={W} height={H} role="img" aria-label="speed against error">
          {logTicks(x0, x1).map((t) => (
            <g>
              <line x1={sx(t)} x2={sx(t)} y1={M.t} y2={H - M.b} class="grid" />
              <text x={sx(t)} y={H - M.b + 16} class="tick" text-anchor="middle">
                {t < 0.001 ? t.toExponential(0) : String(+t.toPrecision(3))}
              </text>
            </g>
          ))}
          {linTicks(y0, y1).map((t) => (
            <g>
              <line x1={M.l} x2={W - M.r} y1={sy(t)} y2={sy(t)} class="grid" />
              <text x={M.l - 6} y={sy(t) + 4} class="tick" text-anchor="end">
                {t}
              </text>
            </g>
          ))}
          <text x={(M.l + W - M.r) / 2} y={H - 8} class="axis-label" text-anchor="middle">
            render time (s, log)
          </text>
          <text x={14} y={(M.t + H - M.b) / 2} class="axis-label" text-anchor="middle" transform={`rotate(-90 14 ${(M.t + H - M.b) / 2})`}>
            {METRICS[metric].label}
          </text>
          {lines.map((l) => (
            <path d={l.d} stroke={colour(l.m)} fill="none" stroke-width={1.5} opacity={0.6} />
          ))}
          {pts.map((p) => (
            <circle
              cx={sx(p.x)}
              cy={sy(p.y)}
              r={hover === p.e ? 7 : 5}
              fill={colour(p.e.mode)}
              stroke="#fff"
              data-testid="plot-point"
              data-mode={p.e.mode}
              onMouseEnter={() => {
                setHover(p.e);
                setAt({ x: sx(p.x), y: sy(p.y) });
              }}
              onMouseLeave={() => setHover(null)}
            />
          ))}
        </svg>
        <div
          class="tooltip"
          data-testid="plot-tooltip"
          hidden={!hover}
          style={{ left: `${(at.x / W) * 100}%`, top: `${(at.y / H) * 100}%` }}
        >
          {hover && (
            <>
              <strong>{hover.mode}</strong> · {hover.spp} spp · {Number(hover.seconds).toFixed(4)} s ·{" "}
              {num(hover.psnr_db_object) !== null ? `${(hover.psnr_db_object as number).toFixed(2)} dB` : "— dB"}
              {metric !== "psnr_db_object" && num(hover[metric]) !== null && ` · ${metric} ${(hover[metric] as number).toFixed(4)}`}
            </>
          )}
        </div>
        </div>
        <div class="legend">
          {modes.map((m) => (
            <span>
              <i style={{ background: colour(m) }} /> {m}
            </span>
          ))}
        </div>
      </div>
    </div>
  );
}
