// New bake: drop (or pick) a USD file, .usdz or .zip bundle, set the bake settings (fields
// generated from the served BakeSettings schema), upload, create the job, open its page.
import { useEffect, useState } from "preact/hooks";
import { api, errorText } from "../api/client";
import { ErrorBox, ErrorText } from "../components/common";
import {
  initialValues,
  type ObjectSchema,
  SettingsForm,
  toSettings,
  useSettingsSchema,
  type Values,
} from "../components/SettingsForm";

const ACCEPT = ".usda,.usdc,.usd,.usdz,.zip";

export function Upload() {
  const [schema, setSchema] = useState<ObjectSchema | null>(null);
  const [values, setValues] = useState<Values>({});
  const [file, setFile] = useState<File | null>(null);
  const [over, setOver] = useState(false);
  const [busy, setBusy] = useState<string | null>(null);
  const [error, setError] = useState<string | null>(null);
  // the job's queue priority (0..100, higher first; JobCreate.priority): not a bake setting
  const [priority, setPriority] = useState(50);

  const served = useSettingsSchema();
  useEffect(() => {
    if (served.error) setError(served.error);
    if (served.schema) {
      setSchema(served.schema);
      setValues(initialValues(served.schema));
    }
  }, [served.schema, served.error]);

  async function submit(e: Event) {
    e.preventDefault();
    if (!file || !schema) return;
    setError(null);
    setBusy("Uploading and checking the asset…");
    const up = await api.POST("/api/v1/assets", {
      body: { file: file as unknown as string },
      bodySerializer: (body) => {
        const fd = new FormData();
        fd.append("file", body.file as unknown as Blob, file.name);
        return fd;
      },
    });
    if (up.error || !up.data) {
      setBusy(null);
      setError(`Upload of ${file.name}: ${errorText(up.error, up.response.status)}`);
      return;
    }
    setBusy("Creating the job…");
    const job = await api.POST("/api/v1/jobs", {
      body: { asset_id: up.data.id, priority, settings: toSettings(schema, values) as never },
    });
    setBusy(null);
    if (job.error || !job.data) {
      setError(`Settings: ${errorText(job.error, job.response.status)}`);
      return;
    }
    location.hash = `#/jobs/${job.data.id}`;
  }

  return (
    <section>
      <h2>New bake</h2>
      <form onSubmit={submit} class="upload">
        <label
          class={over ? "dropzone over" : "dropzone"}
          data-testid="dropzone"
          onDragOver={(e) => {
            e.preventDefault();
            setOver(true);
          }}
          onDragLeave={() => setOver(false)}
          onDrop={(e) => {
            e.preventDefault();
            setOver(false);
            const f = e.dataTransfer?.files?.[0];
            if (f) setFile(f);
          }}
        >
          <input
            type="file"
            accept={ACCEPT}
            data-testid="file-input"
            onChange={(e) => setFile((e.target as HTMLInputElement).files?.[0] ?? null)}
          />
          {file ? (
            <span>
              <strong data-testid="file-name">{file.name}</strong> ({(file.size / 1024).toFixed(1)} KiB) — drop another to replace
            </span>
          ) : (
            <span>Drop a USD file (.usda/.usdc/.usd), a .usdz or a .zip bundle here, or click to choose</span>
          )}
        </label>
        {schema && (
          <details open class="card">
            <summary>
              <strong>Bake settings</strong> <span class="muted small">(changed fields are highlighted)</span>
            </summary>
            <SettingsForm schema={schema} values={values} onChange={setValues} />
          </details>
        )}
        <label class="priority">
          Priority{" "}
          <input
            type="number"
            min={0}
            max={100}
            step={1}
            value={priority}
            data-testid="priority"
            onInput={(e) => setPriority(Math.max(0, Math.min(100, Math.round(Number((e.target as HTMLInputElement).value) || 0))))}
          />{" "}
          <span class="muted small">0–100, higher first; does not change the result</span>
        </label>
        {error && (
          <ErrorBox>
            <span data-testid="upload-error">
              <ErrorText text={error} />
            </span>
          </ErrorBox>
        )}
        <div class="actions">
          {/* the press keeps the focus where it is: Chromium scrolled the page when a focused
              number field lost it to the button mid-click (measured: 322 px between mousedown
              and mouseup), so the release landed elsewhere and the click never submitted */}
          <button
            class="btn primary"
            type="submit"
            data-testid="submit"
            disabled={!file || !schema || busy !== null}
            onMouseDown={(e) => e.preventDefault()}
          >
            {busy ?? "Upload and bake"}
          </button>
          {schema && (
            <button class="btn" type="button" onClick={() => setValues(initialValues(schema))}>
              Reset to defaults
            </button>
          )}
        </div>
      </form>
    </section>
  );
}
