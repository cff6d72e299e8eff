// Login: a tenant's bearer token, checked against the API before it is kept (sessionStorage).
import { useState } from "preact/hooks";
import { api, errorText, setToken } from "../api/client";

export function Login() {
  const [token, setValue] = useState("");
  const [error, setError] = useState<string | null>(null);
  const [busy, setBusy] = useState(false);

  async function submit(e: Event) {
    e.preventDefault();
    setBusy(true);
    setError(null);
    const { error: err, response } = await api.GET("/api/v1/jobs", {
      params: { query: { limit: 1 } },
      headers: { Authorization: `Bearer ${token.trim()}` },
    });
    setBusy(false);
    if (err) {
      setError(errorText(err, response.status));
      return;
    }
    setToken(token.trim());
    location.hash = "#/jobs";
    dispatchEvent(new HashChangeEvent("hashchange"));
  }

  return (
    <div class="login">
      <form class="card login-card" onSubmit={submit}>
        <h1>texelbake</h1>
        <p class="muted">Appearance LOD baking. Sign in with your tenant's API token.</p>
        <label for="token">API token</label>
        <input
          id="token"
          name="token"
          type="password"
          autocomplete="current-password"
          value={token}
          onInput={(e) => setValue((e.target as HTMLInputElement).value)}
          required
        />
        {error && (
          <p class="error" role="alert" data-testid="login-error">
            {error}
          </p>
        )}
        <button class="btn primary" type="submit" disabled={busy || !token.trim()}>
          {busy ? "Checking…" : "Sign in"}
        </button>
      </form>
    </div>
  );
}
