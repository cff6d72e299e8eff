// The real-time viewer of the baked asset (WebGL2): the LOD mesh chosen by distance, the
// Laplacian-BTF maps decoded in a fragment shader with the continuous LOD λ and the weights
// w_k of Eq. 7 (seed 001 §3.4), or the UsdPreviewSurface fallback (albedo + normal map) when
// the bake has no BTF; orbit camera, light direction, exposure, an FPS readout.
import { useEffect, useRef, useState } from "preact/hooks";
import type { JobPublic } from "../api/client";
import { loadF32, loadImage, loadManifest } from "../api/viewer";
import { ErrorBox } from "../components/common";
import { BakeRenderer, type ViewState } from "../viewer/renderer";

declare global {
  interface Window {
    /** The decode check (tests, benchmarks/dashboard.py): f of every atlas texel. */
    texelbakeDecode?: (wi: number[], wo: number[], lambda: number) => number[];
    /** The view check (tests): the current view's f, (u, v, λ) and wo at w x h pixels. */
    texelbakeCapture?: (w: number, h: number) => { f: number[]; uvl: number[]; wo: number[]; eye: number[]; light: number[] };
  }
}

const INITIAL: ViewState = {
  azimuth: 0.6,
  elevation: 0.35,
  distance: 3.2,
  lightAzimuth: 0.9,
  lightElevation: 0.8,
  exposure: 1.0,
  lambdaBias: 0,
  mode: "btf",
  lod: -1,
};

export function Viewer({ job }: { job: JobPublic }) {
  const canvas = useRef<HTMLCanvasElement>(null);
  const renderer = useRef<BakeRenderer | null>(null);
  const [view, setView] = useState<ViewState>(INITIAL);
  const viewRef = useRef(view);
  viewRef.current = view;
  const [status, setStatus] = useState("Loading the baked asset…");
  const [error, setError] = useState<string | null>(null);
  const [fps, setFps] = useState(0);
  const [spin, setSpin] = useState(false);
  const [lod, setLod] = useState(0);
  const [ready, setReady] = useState(false);
  const drag = useRef<{ x: number; y: number; v: ViewState } | null>(null);

  useEffect(() => {
    let alive = true;
    (async () => {
      try {
        const m = await loadManifest(job.id);
        const [lods, frames, albedo, normal] = await Promise.all([
          Promise.all(m.lods.map((l) => loadF32(job.id, l.file))),
          loadF32(job.id, m.frames),
          loadImage(job.id, "albedo.png"),
          loadImage(job.id, "normal.png"),
        ]);
        const btf = m.btf
          ? await (async () => {
              const b = m.btf!;
              const [weights, eigen, lut, pairIndex, meanTable] = await Promise.all(
                [b.weights, b.eigen, b.lut, b.pair_index, b.mean_table].map((r) => loadF32(job.id, r.file)),
              );
              return { weights, eigen, lut, pairIndex, meanTable };
            })()
          : null;
        if (!alive || !canvas.current) return;
        const r = new BakeRenderer(canvas.current, { manifest: m, lods, frames, albedo, normal, btf });
        renderer.current = r;
        window.texelbakeDecode = (wi, wo, lambda) => Array.from(r.decode(wi, wo, lambda));
        window.texelbakeCapture = (w, h) => {
          const c = r.capture(viewRef.current, w, h);
          r.draw(viewRef.current);
          return { f: Array.from(c.f), uvl: Array.from(c.uvl), wo: Array.from(c.wo), eye: c.eye, light: c.light };
        };
        if (!r.hasBtf) setView((v) => ({ ...v, mode: "preview" }));
        setStatus(
          r.hasBtf
            ? `BTF: ${m.btf!.n_components.join("+")} components, λ_max ${m.btf!.top_level}, ${m.btf!.num_pairs} direction pairs`
            : "No BTF maps in this bake (bake with btf on): UsdPreviewSurface fallback",
        );
        setReady(true);
      } catch (e) {
        setError((e as Error).message);
      }
    })();
    return () => {
      alive = false;
      delete window.texelbakeDecode;
      delete window.texelbakeCapture;
    };
  }, [job.id]);

  // the render loop: every animation frame while spinning, else when the view changes
  useEffect(() => {
    if (!ready) return;
    let raf = 0;
    let frames = 0;
    let t0 = performance.now();
    const tick = () => {
      const r = renderer.current;
      if (!r) return;
      if (spin) viewRef.current = { ...viewRef.current, azimuth: viewRef.current.azimuth + 0.01 };
      r.draw(viewRef.current);
      if (!spin) setLod(r.lastLod);
      frames += 1;
      const now = performance.now();
      if (now - t0 >= 1000) {
        setFps((frames * 1000) / (now - t0));
        setLod(r.lastLod);
        frames = 0;
        t0 = now;
      }
      if (spin) raf = requestAnimationFrame(tick);
    };
    raf = requestAnimationFrame(tick);
    return () => cancelAnimationFrame(raf);
  }, [ready, spin, view]);

  const set = (patch: Partial<ViewState>) => setView((v) => ({ ...v, ...patch }));
  const slider = (label: string, key: keyof ViewState, min: number, max: number, step: number) => (
    <label class="slider">
      {label}
      <input
        type="range"
        min={min}
        max={max}
        step={step}
        value={view[key] as number}
        data-testid={`viewer-${key}`}
        onInput={(e) => set({ [key]: +(e.target as HTMLInputElement).value } as Partial<ViewState>)}
      />
    </label>
  );
  if (error) return <ErrorBox>{error}</ErrorBox>;
  return (
    <div class="viewer" data-testid="viewer" data-ready={ready ? "1" : "0"}>
      <p class="muted small" data-testid="viewer-status">{status}</p>
      <div class="viewer-row">
        <div class="viewer-canvas-wrap">
          <canvas
            ref={canvas}
            width={640}
            height={480}
            class="viewer-canvas"
            data-testid="viewer-canvas"
            onMouseDown={(e) => (drag.current = { x: e.clientX, y: e.clientY, v: view })}
            onMouseMove={(e) => {
              const d = drag.current;
              if (!d) return;
              set({
                azimuth: d.v.azimuth - (e.clientX - d.x) * 0.01,
                elevation: Math.max(-1.5, Math.min(1.5, d.v.elevation + (e.clientY - d.y) * 0.01)),
              });
            }}
            onMouseUp={() => (drag.current = null)}
            onMouseLeave={() => (drag.current = null)}
            onWheel={(e) => {
              e.preventDefault();
              set({ distance: Math.max(1.2, Math.min(64, view.distance * (e.deltaY > 0 ? 1.15 : 1 / 1.15))) });
            }}
          />
          <div class="hud" data-testid="viewer-hud">
            {spin ? `${fps.toFixed(1)} fps` : "idle (drag to orbit, wheel to zoom)"} · LOD M{lod + 1} · distance{" "}
            {view.distance.toFixed(1)} r
          </div>
        </div>
        <div class="card viewer-controls">
          <label>
            Shading{" "}
            <select data-testid="viewer-mode" value={view.mode} onChange={(e) => set({ mode: (e.target as HTMLSelectElement).value as ViewState["mode"] })}>
              <option value="btf" disabled={!renderer.current?.hasBtf}>
                Laplacian BTF (Eq. 7)
              </option>
              <option value="preview">UsdPreviewSurface (albedo + normal map)</option>
            </select>
          </label>
          <label>
            LOD mesh{" "}
            <select data-testid="viewer-lod" value={String(view.lod)} onChange={(e) => set({ lod: +(e.target as HTMLSelectElement).value })}>
              <option value="-1">by distance</option>
              {Array.from({ length: renderer.current?.lodCount ?? 0 }, (_, i) => (
                <option value={String(i)}>M{i + 1}</option>
              ))}
            </select>
          </label>
          <p class="muted small">
            The BTF lives on M1's atlas and texel frames; coarser meshes look it up through
            their transferred uvs, so faces far from M1 can fall below a texel's horizon (black).
          </p>
          {slider("Light azimuth", "lightAzimuth", -3.14, 3.14, 0.01)}
          {slider("Light elevation", "lightElevation", 0.05, 1.55, 0.01)}
          {slider("Exposure", "exposure", 0.1, 4, 0.05)}
          {slider("λ bias", "lambdaBias", -2, 4, 0.1)}
          {slider("Distance (radii)", "distance", 1.2, 64, 0.1)}
          <label>
            <input type="checkbox" data-testid="viewer-spin" checked={spin} onChange={(e) => setSpin((e.target as HTMLInputElement).checked)} /> rotate
            continuously (measures fps)
          </label>
        </div>
      </div>
    </div>
  );
}
