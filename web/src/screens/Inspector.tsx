// The per-texel inspector: the finest CPM level's atlas as a map (points, held-out SNR or
// the albedo); click a texel to see its characteristic points, rank, held-out and in-sample
// SNR, and its a_vis (seed 000 §3.4) as a polar plot over the view directions of its frame.
import { useEffect, useRef, useState } from "preact/hooks";
import type { JobPublic } from "../api/client";
import { loadF32, loadImage, loadManifest, loadTexels, type Manifest, type Texels } from "../api/viewer";
import { css, viridis } from "../components/colormap";
import { ErrorBox } from "../components/common";

type MapKind = "points" | "snr" | "albedo";
const SIZE = 384;

export function Inspector({ job }: { job: JobPublic }) {
  const [man, setMan] = useState<Manifest | null>(null);
  const [tex, setTex] = useState<Texels | null>(null);
  const [avis, setAvis] = useState<Float32Array | null>(null);
  const [albedo, setAlbedo] = useState<ImageBitmap | null>(null);
  const [error, setError] = useState<string | null>(null);
  const [kind, setKind] = useState<MapKind>("points");
  const [sel, setSel] = useState<{ row: number; col: number } | null>(null);
  const canvas = useRef<HTMLCanvasElement>(null);

  useEffect(() => {
    (async () => {
      try {
        const m = await loadManifest(job.id);
        const [t, a, img] = await Promise.all([
          loadTexels(job.id),
          loadF32(job.id, m.avis.file),
          loadImage(job.id, "albedo.png"),
        ]);
        setMan(m);
        setTex(t);
        setAvis(a);
        setAlbedo(img);
      } catch (e) {
        setError((e as Error).message);
      }
    })();
  }, [job.id]);

  const n = tex?.n ?? 0;
  const values = (): (number | null)[] =>
    !tex ? [] : kind === "points" ? tex.points : kind === "snr" ? tex.snr_heldout_db : [];
  const finite = values().filter((v): v is number => v !== null && Number.isFinite(v));
  const lo = finite.length ? Math.min(...finite) : 0;
  const hi = finite.length ? Math.max(...finite) : 1;

  useEffect(() => {
    const c = canvas.current;
    if (!c || !tex) return;
    c.width = n;
    c.height = n;
    const ctx = c.getContext("2d")!;
    if (kind === "albedo" && albedo) {
      ctx.drawImage(albedo, 0, 0, n, n);
    } else {
      const img = ctx.createImageData(n, n);
      const vals = values();
      for (let i = 0; i < n * n; i++) {
        const v = vals[i];
        const rgb = v === null || v === undefined ? ([40, 40, 40] as [number, number, number]) : viridis((v - lo) / Math.max(hi - lo, 1e-9));
        img.data.set([rgb[0], rgb[1], rgb[2], 255], i * 4);
      }
      ctx.putImageData(img, 0, 0);
    }
  }, [tex, kind, albedo]);

  if (error) return <ErrorBox>{error}</ErrorBox>;
  if (!man || !tex || !avis) return <p class="muted">Extracting the texel data from the baked USD…</p>;

  function pick(e: MouseEvent) {
    const r = (e.currentTarget as HTMLElement).getBoundingClientRect();
    const col = Math.min(n - 1, Math.floor(((e.clientX - r.left) / r.width) * n));
    const row = Math.min(n - 1, Math.floor(((e.clientY - r.top) / r.height) * n));
    setSel({ row, col });
  }
  const t = sel ? sel.row * n + sel.col : -1;
  const fmt = (v: number | null) => (v === null ? "—" : `${v.toFixed(2)} dB`);
  return (
    <div class="inspector" data-testid="inspector">
      <div class="filters">
        <label>
          Map{" "}
          <select data-testid="inspector-map" value={kind} onChange={(e) => setKind((e.target as HTMLSelectElement).value as MapKind)}>
            <option value="points">characteristic points per texel</option>
            <option value="snr">held-out SNR (dB)</option>
            <option value="albedo">albedo (fallback map)</option>
          </select>
        </label>
        {kind !== "albedo" && (
          <span class="muted small">
            {lo.toFixed(kind === "points" ? 0 : 1)} … {hi.toFixed(kind === "points" ? 0 : 1)} (viridis)
          </span>
        )}
        <span class="muted small">
          finest level: {n}×{n} texels of M1's atlas · click a texel
        </span>
      </div>
      <div class="inspector-row">
        <div class="atlas-wrap">
          <canvas ref={canvas} class="atlas" data-testid="atlas" width={n} height={n} style={{ width: `${SIZE}px`, height: `${SIZE}px` }} onClick={pick} />
          {sel && (
            <div
              class="atlas-cursor"
              style={{ left: `${(sel.col / n) * SIZE}px`, top: `${(sel.row / n) * SIZE}px`, width: `${SIZE / n}px`, height: `${SIZE / n}px` }}
            />
          )}
        </div>
        {sel ? (
          <div class="card texel-card" data-testid="texel-info" data-row={sel.row} data-col={sel.col}>
            <h3>
              Texel ({sel.row}, {sel.col})
            </h3>
            <dl class="kv">
              <dt>characteristic points</dt>
              <dd data-testid="texel-points">{tex.points[t]}</dd>
              <dt>rank k</dt>
              <dd>{tex.k[t]}</dd>
              <dt>held-out SNR</dt>
              <dd data-testid="texel-snr">{fmt(tex.snr_heldout_db[t])}</dd>
              <dt>in-sample SNR</dt>
              <dd>{fmt(tex.snr_insample_db[t])}</dd>
              <dt>valid</dt>
              <dd>{tex.valid[t] ? "yes" : "no (empty texel)"}</dd>
            </dl>
            <h4>a_vis / texel area over view directions (texel frame)</h4>
            <PolarPlot values={avis.subarray(t * man.avis.n_theta * man.avis.n_phi, (t + 1) * man.avis.n_theta * man.avis.n_phi)} nTheta={man.avis.n_theta} nPhi={man.avis.n_phi} />
          </div>
        ) : (
          <p class="muted">Click a texel of the atlas.</p>
        )}
      </div>
    </div>
  );
}

/** A polar heat map: rings are theta (centre = the normal, rim = the horizon), sectors phi. */
export function PolarPlot({ values, nTheta, nPhi }: { values: Float32Array; nTheta: number; nPhi: number }) {
  const R = 120;
  const max = Math.max(1e-9, ...Array.from(values));
  const cells = [];
  for (let i = 0; i < nTheta; i++)
    for (let j = 0; j < nPhi; j++) {
      const r0 = (i / nTheta) * R;
      const r1 = ((i + 1) / nTheta) * R;
      const a0 = (j / nPhi) * 2 * Math.PI;
      const a1 = ((j + 1) / nPhi) * 2 * Math.PI;
      const p = (r: number, a: number) => `${(R + 10 + r * Math.cos(a)).toFixed(2)},${(R + 10 - r * Math.sin(a)).toFixed(2)}`;
      const v = values[i * nPhi + j];
      cells.push(
        <path
          d={`M${p(r0, a0)} L${p(r1, a0)} A${r1},${r1} 0 0 0 ${p(r1, a1)} L${p(r0, a1)} A${r0},${r0} 0 0 1 ${p(r0, a0)} Z`}
          fill={css(viridis(v / max))}
          data-value={v}
        >
          <title>
            θ {(((i + 0.5) / nTheta) * 90).toFixed(1)}°, φ {(((j + 0.5) / nPhi) * 360).toFixed(0)}°: {v.toFixed(4)}
          </title>
        </path>,
      );
    }
  return (
    <svg class="polar" data-testid="avis-polar" viewBox={`0 0 ${2 * R + 44} ${2 * R + 20}`} width={2 * R + 44} height={2 * R + 20}>
      {cells}
      <circle cx={R + 10} cy={R + 10} r={R} fill="none" stroke="#888" />
      <text x={R + 10} y={R + 14} text-anchor="middle" class="tick">n</text>
      <text x={2 * R + 12} y={R + 6} class="tick">φ=0</text>
      <text x={R + 10} y={2 * R + 19} text-anchor="middle" class="tick">max {max.toFixed(3)}</text>
    </svg>
  );
}
