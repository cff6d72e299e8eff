// Is the bake good? Every mode's preview side by side with synchronised zoom/pan, a swipe or
// difference view of any two, and the diagnostic maps (mip levels, point density).
import { useEffect, useRef, useState } from "preact/hooks";
import type { JobPublic } from "../api/client";
import { ErrorBox } from "../components/common";
import { useBlobUrls } from "../components/useBlobUrls";
import { IDENTITY, type View, ZoomPanView } from "../components/ZoomPan";

/** Preview modes in display order; the reference first. */
export const MODES = ["gt_reference", "gt", "cpm", "normalmap", "equal-time", "btf"];
const DIAGNOSTICS = ["mip_levels.png", "cp_density_atlas.png", "cp_density_model.png"];
/** The deformed frames (the `deformed` stage: the asset's animation or a warp's sweep). */
const DEFORMED = ["animation.gif", "error_per_frame.png"];
const VIEWS: Record<string, string> = { near: "", far: "far_" };

export function Previews({ job }: { job: JobPublic }) {
  const names = new Set(job.previews ?? []);
  const [viewName, setViewName] = useState<"near" | "far">("near");
  const prefix = VIEWS[viewName];
  const modes = MODES.filter((m) => names.has(`${prefix}${m}.png`));
  const diags = DIAGNOSTICS.map((d) => (d.startsWith("mip") ? `${prefix}${d}` : d)).filter((d) => names.has(d));
  const deformed = DEFORMED.filter((d) => names.has(d));
  const wanted = [...modes.map((m) => `${prefix}${m}.png`), ...diags, ...deformed];
  const { urls, error } = useBlobUrls(job.id, wanted);
  const [view, setView] = useState<View>(IDENTITY);
  // the diagnostics zoom together too, apart from the renders (the atlas is another space)
  const [diagView, setDiagView] = useState<View>(IDENTITY);
  const [a, setA] = useState("gt_reference");
  const [b, setB] = useState("cpm");
  const [compare, setCompare] = useState<"swipe" | "difference">("swipe");
  const [swipe, setSwipe] = useState(0.5);
  const [gain, setGain] = useState(4);

  if (error) return <ErrorBox>{error}</ErrorBox>;
  const ua = urls[`${prefix}${a}.png`];
  const ub = urls[`${prefix}${b}.png`];
  return (
    <div class="previews" data-testid="previews">
      <div class="filters">
        <label>
          View{" "}
          <select value={viewName} onChange={(e) => setViewName((e.target as HTMLSelectElement).value as "near" | "far")}>
            <option value="near">near (the asset's camera)</option>
            <option value="far">far (where the maps apply)</option>
          </select>
        </label>
        <span class="muted small">Wheel: zoom · drag: pan · double click: reset (all panels move together)</span>
        <button class="btn" onClick={() => setView(IDENTITY)}>
          Reset zoom
        </button>
      </div>
      <div class="preview-grid">
        {modes.map((m) => (
          <figure class="preview" data-testid="preview" data-mode={m}>
            <ZoomPanView view={view} onView={setView}>
              {urls[`${prefix}${m}.png`] && <img src={urls[`${prefix}${m}.png`]} alt={m} draggable={false} />}
            </ZoomPanView>
            <figcaption>{m === "gt_reference" ? "gt (reference)" : m}</figcaption>
          </figure>
        ))}
      </div>
      <h3>Compare</h3>
      <div class="filters">
        <label>
          A{" "}
          <select data-testid="compare-a" value={a} onChange={(e) => setA((e.target as HTMLSelectElement).value)}>
            {modes.map((m) => (
              <option value={m}>{m}</option>
            ))}
          </select>
        </label>
        <label>
          B{" "}
          <select data-testid="compare-b" value={b} onChange={(e) => setB((e.target as HTMLSelectElement).value)}>
            {modes.map((m) => (
              <option value={m}>{m}</option>
            ))}
          </select>
        </label>
        <label>
          <input type="radio" name="cmp" checked={compare === "swipe"} onChange={() => setCompare("swipe")} /> swipe
        </label>
        <label>
          <input
            type="radio"
            name="cmp"
            data-testid="compare-difference"
            checked={compare === "difference"}
            onChange={() => setCompare("difference")}
          />{" "}
          difference
        </label>
        {compare === "swipe" ? (
          <label>
            split{" "}
            <input type="range" min={0} max={1} step={0.01} value={swipe} onInput={(e) => setSwipe(+(e.target as HTMLInputElement).value)} />
          </label>
        ) : (
          <label>
            gain ×{gain}{" "}
            <input type="range" min={1} max={32} step={1} value={gain} onInput={(e) => setGain(+(e.target as HTMLInputElement).value)} />
          </label>
        )}
      </div>
      <div class="compare-row">
        <figure class="preview large" data-testid="compare-view" data-compare={compare}>
          <ZoomPanView view={view} onView={setView}>
            {ua && ub && compare === "swipe" && (
              <div class="swipe">
                <img src={ua} alt={a} draggable={false} />
                <img src={ub} alt={b} draggable={false} style={{ clipPath: `inset(0 0 0 ${swipe * 100}%)` }} />
                <div class="swipe-line" style={{ left: `${swipe * 100}%` }} />
              </div>
            )}
            {ua && ub && compare === "difference" && <DiffCanvas a={ua} b={ub} gain={gain} />}
          </ZoomPanView>
          <figcaption>
            {compare === "swipe" ? `${a} | ${b}` : `|${a} − ${b}| × ${gain} (sRGB values)`}
          </figcaption>
        </figure>
        {names.has(`${prefix}diff_${b}.png`) && <DiffFile job={job} name={`${prefix}diff_${b}.png`} view={view} onView={setView} />}
      </div>
      {deformed.length > 0 && (
        <>
          <h3>Deformed frames</h3>
          <p class="muted small">
            The asset's animation, or the warp's sweep from the rest pose: the reference, cpm, cpm-naive and the normal map, left to
            right; PSNR over the object per frame.
          </p>
          <div class="deformed-row">
            {deformed.map((d) => (
              <figure class="preview" data-testid="deformed">
                {urls[d] && <img src={urls[d]} alt={d} draggable={false} class={d.endsWith(".gif") ? "blocks" : undefined} />}
                <figcaption>{d === "animation.gif" ? "animation" : "error per frame"}</figcaption>
              </figure>
            ))}
          </div>
        </>
      )}
      {diags.length > 0 && (
        <>
          <h3>Diagnostics</h3>
          <div class="preview-grid">
            {diags.map((d) => (
              <figure class="preview" data-testid="diagnostic">
                <ZoomPanView view={diagView} onView={setDiagView}>
                  {urls[d] && <img src={urls[d]} alt={d} draggable={false} />}
                </ZoomPanView>
                <figcaption>{d.replace(/\.png$/, "").replace(/_/g, " ")}</figcaption>
              </figure>
            ))}
          </div>
        </>
      )}
    </div>
  );
}

function DiffFile({ job, name, view, onView }: { job: JobPublic; name: string; view: View; onView: (v: View) => void }) {
  const { urls } = useBlobUrls(job.id, [name]);
  return (
    <figure class="preview large">
      <ZoomPanView view={view} onView={onView}>
        {urls[name] && <img src={urls[name]} alt={name} draggable={false} />}
      </ZoomPanView>
      <figcaption>ΔE*ab against the reference ({name})</figcaption>
    </figure>
  );
}

function loadImage(url: string): Promise<HTMLImageElement> {
  return new Promise((res, rej) => {
    const img = new Image();
    img.onload = () => res(img);
    img.onerror = () => rej(new Error(`cannot decode ${url}`));
    img.src = url;
  });
}

/** |A − B| per channel of the two sRGB images, times `gain`, drawn into a canvas. */
function DiffCanvas({ a, b, gain }: { a: string; b: string; gain: number }) {
  const ref = useRef<HTMLCanvasElement>(null);
  useEffect(() => {
    let alive = true;
    (async () => {
      const [ia, ib] = await Promise.all([loadImage(a), loadImage(b)]);
      const c = ref.current;
      if (!alive || !c) return;
      const w = Math.min(ia.naturalWidth, ib.naturalWidth);
      const h = Math.min(ia.naturalHeight, ib.naturalHeight);
      c.width = w;
      c.height = h;
      const ctx = c.getContext("2d", { willReadFrequently: true })!;
      ctx.drawImage(ia, 0, 0);
      const da = ctx.getImageData(0, 0, w, h);
      ctx.drawImage(ib, 0, 0);
      const db = ctx.getImageData(0, 0, w, h);
      const out = ctx.createImageData(w, h);
      for (let i = 0; i < out.data.length; i += 4) {
        out.data[i] = Math.min(255, Math.abs(da.data[i] - db.data[i]) * gain);
        out.data[i + 1] = Math.min(255, Math.abs(da.data[i + 1] - db.data[i + 1]) * gain);
        out.data[i + 2] = Math.min(255, Math.abs(da.data[i + 2] - db.data[i + 2]) * gain);
        out.data[i + 3] = 255;
      }
      ctx.putImageData(out, 0, 0);
    })();
    return () => {
      alive = false;
    };
  }, [a, b, gain]);
  return <canvas ref={ref} class="diff-canvas" data-testid="diff-canvas" />;
}
