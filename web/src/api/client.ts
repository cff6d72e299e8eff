// The typed API client: generated types (schema.d.ts, from the served OpenAPI schema by
// openapi-typescript) + openapi-fetch. Every request carries the bearer token.
import createClient, { type Middleware } from "openapi-fetch";
import type { components, paths } from "./schema";

export type Schemas = components["schemas"];
export type JobPublic = Schemas["JobPublic"];
export type JobSummary = Schemas["JobSummary"];
export type StagePublic = Schemas["StagePublic"];
export type ShardPublic = Schemas["ShardPublic"];
export type FarmPublic = Schemas["FarmPublic"];
export type JobState = JobPublic["state"];
export type ErrorPublic = Schemas["ErrorPublic"];

const TOKEN_KEY = "texelbake.token";

export function getToken(): string | null {
  return sessionStorage.getItem(TOKEN_KEY);
}

export function setToken(token: string | null): void {
  if (token) sessionStorage.setItem(TOKEN_KEY, token);
  else sessionStorage.removeItem(TOKEN_KEY);
}

export const TERMINAL: ReadonlySet<string> = new Set(["succeeded", "failed", "cancelled"]);

const auth: Middleware = {
  onRequest({ request }) {
    const token = getToken();
    if (token) request.headers.set("Authorization", `Bearer ${token}`);
    return request;
  },
  onResponse({ response }) {
    if (response.status === 401 && getToken()) {
      setToken(null);
      location.hash = "#/login";
    }
    return response;
  },
};

export const api = createClient<paths>({ baseUrl: "" });
api.use(auth);

/** The message of an error body (`ErrorPublic`), whatever its `detail` holds. */
export function errorText(err: unknown, status?: number): string {
  const e = err as Partial<ErrorPublic> | undefined;
  if (e && e.detail !== undefined) {
    const d = e.detail as unknown;
    if (typeof d === "string") return `${d}${e.code ? ` (${e.code})` : ""}`;
    if (Array.isArray(d))
      return d
        .map((x: { loc?: unknown[]; msg?: string }) => `${(x.loc ?? []).join(".")}: ${x.msg}`)
        .join("; ");
    return JSON.stringify(d);
  }
  return status ? `HTTP ${status}` : String(err);
}

/** A binary file of the API (previews, the result zip) as a Blob, with the bearer token. */
export async function fetchBlob(url: string): Promise<Blob> {
  const token = getToken();
  const r = await fetch(url, { headers: token ? { Authorization: `Bearer ${token}` } : {} });
  if (!r.ok) {
    let body: unknown;
    try {
      body = await r.json();
    } catch {
      body = undefined;
    }
    throw new Error(errorText(body, r.status));
  }
  return r.blob();
}

export function previewUrl(jobId: string, name: string): string {
  return `/api/v1/jobs/${encodeURIComponent(jobId)}/previews/${encodeURIComponent(name)}`;
}
