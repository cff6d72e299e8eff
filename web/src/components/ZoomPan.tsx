// Synchronised zoom and pan: every <ZoomPanView> given the same view state shows the same
// region; the wheel zooms about the cursor, a drag pans, a double click resets.
import type { ComponentChildren } from "preact";
import { useRef } from "preact/hooks";

export interface View {
  scale: number;
  x: number;
  y: number;
}

export const IDENTITY: View = { scale: 1, x: 0, y: 0 };

export function zoomAt(v: View, factor: number, px: number, py: number): View {
  const scale = Math.max(1, Math.min(32, v.scale * factor));
  const k = scale / v.scale;
  return clampView({ scale, x: px - (px - v.x) * k, y: py - (py - v.y) * k }, 1, 1);
}

/** Keep the content covering the viewport (size w x h in the same units as x, y). */
export function clampView(v: View, w: number, h: number): View {
  const minX = w - w * v.scale;
  const minY = h - h * v.scale;
  return { scale: v.scale, x: Math.min(0, Math.max(minX, v.x)), y: Math.min(0, Math.max(minY, v.y)) };
}

export function ZoomPanView({
  view,
  onView,
  children,
  testid,
}: {
  view: View;
  onView: (v: View) => void;
  children: ComponentChildren;
  testid?: string;
}) {
  const ref = useRef<HTMLDivElement>(null);
  const drag = useRef<{ x: number; y: number; v: View } | null>(null);
  // positions as fractions of the viewport, so views of different pixel sizes stay in step
  const frac = (e: MouseEvent) => {
    const r = ref.current!.getBoundingClientRect();
    return { fx: (e.clientX - r.left) / r.width, fy: (e.clientY - r.top) / r.height, r };
  };
  return (
    <div
      ref={ref}
      class="zoompan"
      data-testid={testid}
      onWheel={(e) => {
        e.preventDefault();
        const { fx, fy } = frac(e);
        onView(zoomAt(view, e.deltaY < 0 ? 1.25 : 0.8, fx, fy));
      }}
      onMouseDown={(e) => {
        e.preventDefault();
        drag.current = { x: e.clientX, y: e.clientY, v: view };
      }}
      onMouseMove={(e) => {
        const d = drag.current;
        if (!d) return;
        const r = ref.current!.getBoundingClientRect();
        onView(
          clampView(
            { scale: d.v.scale, x: d.v.x + (e.clientX - d.x) / r.width, y: d.v.y + (e.clientY - d.y) / r.height },
            1,
            1,
          ),
        );
      }}
      onMouseUp={() => (drag.current = null)}
      onMouseLeave={() => (drag.current = null)}
      onDblClick={() => onView(IDENTITY)}
    >
      <div
        class="zoompan-inner"
        style={{ transform: `translate(${view.x * 100}%, ${view.y * 100}%) scale(${view.scale})` }}
      >
        {children}
      </div>
    </div>
  );
}
