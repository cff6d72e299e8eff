// Bake settings fields generated from the JSON Schema of BakeSettings as the API serves it
// (components.schemas.BakeSettings of /api/v1/openapi.json): a field per property, its type,
// bounds, choices, default and description from the schema, shown in the settings' groups
// (each property's `group`, in the order the schema lists them).
import { useEffect, useState } from "preact/hooks";

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
  /** the settings group (geometry, fit, a_vis, ...) the API schema files the field under */
  group?: string;
}

export interface ObjectSchema {
  properties: Record<string, JsonSchemaProp>;
  description?: string;
}

export type Values = Record<string, string | boolean>;

/** The served BakeSettings schema (components.schemas.BakeSettings of the API's OpenAPI). */
export function useSettingsSchema(): { schema: ObjectSchema | null; error: string | null } {
  const [schema, setSchema] = useState<ObjectSchema | null>(null);
  const [error, setError] = useState<string | null>(null);
  useEffect(() => {
    (async () => {
      const r = await fetch("/api/v1/openapi.json");
      if (!r.ok) {
        setError(`cannot read the API schema: HTTP ${r.status}`);
        return;
      }
      const spec = await r.json();
      const s = spec?.components?.schemas?.BakeSettings as ObjectSchema | undefined;
      if (!s?.properties) {
        setError("the API schema has no BakeSettings");
        return;
      }
      setSchema(s);
    })();
  }, []);
  return { schema, error };
}

/** The schema's properties by group, groups and fields in the schema's order. */
export function groupedProps(schema: ObjectSchema): [string, [string, JsonSchemaProp][]][] {
  const groups = new Map<string, [string, JsonSchemaProp][]>();
  for (const [k, p] of Object.entries(schema.properties)) {
    const g = p.group ?? "settings";
    if (!groups.has(g)) groups.set(g, []);
    groups.get(g)!.push([k, p]);
  }
  return [...groups.entries()];
}

/** Whether a stored setting's value is the schema's default for it. */
export function isDefault(p: JsonSchemaProp | undefined, v: unknown): boolean {
  return p !== undefined && JSON.stringify(v) === JSON.stringify(p.default);
}

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
  const field = ([k, p]: [string, JsonSchemaProp]) => {
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
  };
  return (
    <div data-testid="settings-form">
      {groupedProps(schema).map(([group, props]) => (
        <fieldset class="settings-group" data-group={group}>
          <legend>{group}</legend>
          <div class="settings-form">{props.map(field)}</div>
        </fieldset>
      ))}
    </div>
  );
}
