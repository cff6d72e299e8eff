// Bake settings fields generated from the JSON Schema of BakeSettings as the API serves it
// (components.schemas.BakeSettings of /api/v1/openapi.json): a field per property, its type,
// bounds, choices, default and description from the schema.

export interface JsonSchemaProp {
  type?: string;
  enum?: (string | number)[];
  default?: unknown;
  description?: string;
  title?: string;
  minimum?: number;
  maximum?: number;
  exclusiveMinimum?: number;
  exclusiveMaximum?: number;
}

export interface ObjectSchema {
  properties: Record<string, JsonSchemaProp>;
  description?: string;
}

export type Values = Record<string, string | boolean>;

export function initialValues(schema: ObjectSchema): Values {
  const out: Values = {};
  for (const [k, p] of Object.entries(schema.properties))
    out[k] = p.type === "boolean" ? Boolean(p.default) : p.default === undefined ? "" : String(p.default);
  return out;
}

/** The settings object to send: only fields that differ from their default. */
export function toSettings(schema: ObjectSchema, values: Values): Record<string, unknown> {
  const out: Record<string, unknown> = {};
  for (const [k, p] of Object.entries(schema.properties)) {
    const v = values[k];
    let parsed: unknown = v;
    if (p.type === "integer") parsed = Number.parseInt(String(v), 10);
    else if (p.type === "number") parsed = Number.parseFloat(String(v));
    else if (p.type === "array") {
      // a list of numbers typed as "256,64"; anything unparsable goes as typed (the API names it)
      const items = String(v).split(",").map((x) => x.trim()).filter((x) => x !== "").map(Number);
      parsed = items.some((x) => Number.isNaN(x)) ? v : items;
      if (JSON.stringify(parsed) !== JSON.stringify(p.default)) out[k] = parsed;
      continue;
    }
    if (parsed !== p.default && !(typeof parsed === "number" && Number.isNaN(parsed))) out[k] = parsed;
    else if (typeof parsed === "number" && Number.isNaN(parsed)) out[k] = v; // the API names it
  }
  return out;
}

export function SettingsForm({
  schema,
  values,
  onChange,
}: {
  schema: ObjectSchema;
  values: Values;
  onChange: (v: Values) => void;
}) {
  const set = (k: string, v: string | boolean) => onChange({ ...values, [k]: v });
  return (
    <div class="settings-form" data-testid="settings-form">
      {Object.entries(schema.properties).map(([k, p]) => {
        const id = `setting-${k}`;
        const changed =
          p.type === "boolean" ? values[k] !== Boolean(p.default) : String(values[k]) !== String(p.default ?? "");
        let input;
        if (p.enum) {
          input = (
            <select id={id} name={k} value={String(values[k])} onChange={(e) => set(k, (e.target as HTMLSelectElement).value)}>
              {p.enum.map((o) => (
                <option value={String(o)}>{String(o)}</option>
              ))}
            </select>
          );
        } else if (p.type === "boolean") {
          input = (
            <input id={id} name={k} type="checkbox" checked={Boolean(values[k])} onChange={(e) => set(k, (e.target as HTMLInputElement).checked)} />
          );
        } else {
          const numeric = p.type === "integer" || p.type === "number";
          input = (
            <input
              id={id}
              name={k}
              type={numeric ? "number" : "text"}
              step={p.type === "integer" ? 1 : "any"}
              min={p.minimum ?? p.exclusiveMinimum}
              max={p.maximum ?? p.exclusiveMaximum}
              value={String(values[k])}
              onInput={(e) => set(k, (e.target as HTMLInputElement).value)}
            />
          );
        }
        const bounds = [
          p.minimum !== undefined ? `≥ ${p.minimum}` : p.exclusiveMinimum !== undefined ? `> ${p.exclusiveMinimum}` : "",
          p.maximum !== undefined ? `≤ ${p.maximum}` : p.exclusiveMaximum !== undefined ? `< ${p.exclusiveMaximum}` : "",
        ]
          .filter(Boolean)
          .join(", ");
        return (
          <div class={changed ? "field changed" : "field"} data-field={k}>
            <label for={id}>
              <span class="field-name mono">{k}</span>
              {input}
            </label>
            <div class="field-help small">
              {p.description && <span>{p.description} </span>}
              <span class="muted">
                default {p.default === undefined ? "—" : String(p.default)}
                {bounds && ` · ${bounds}`}
              </span>
            </div>
          </div>
        );
      })}
    </div>
  );
}
