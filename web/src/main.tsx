// The dashboard: a hash router over one module per screen.
import { render } from "preact";
import { useEffect, useState } from "preact/hooks";
import { getToken, setToken } from "./api/client";
import { Farm } from "./screens/Farm";
import { JobPage } from "./screens/JobPage";
import { JobsList } from "./screens/JobsList";
import { Login } from "./screens/Login";
import { Upload } from "./screens/Upload";
import "./styles.css";

export type Route =
  | { name: "login" }
  | { name: "jobs" }
  | { name: "job"; id: string; tab: string }
  | { name: "upload" }
  | { name: "farm" };

export function parseRoute(hash: string): Route {
  const parts = hash.replace(/^#\/?/, "").split("/").filter(Boolean).map(decodeURIComponent);
  if (parts[0] === "login") return { name: "login" };
  if (parts[0] === "jobs" && parts[1]) return { name: "job", id: parts[1], tab: parts[2] ?? "overview" };
  if (parts[0] === "upload") return { name: "upload" };
  if (parts[0] === "farm") return { name: "farm" };
  return { name: "jobs" };
}

function useRoute(): Route {
  const [route, setRoute] = useState(parseRoute(location.hash));
  useEffect(() => {
    const on = () => setRoute(parseRoute(location.hash));
    addEventListener("hashchange", on);
    return () => removeEventListener("hashchange", on);
  }, []);
  return route;
}

function App() {
  const route = useRoute();
  const token = getToken();
  if (!token || route.name === "login") return <Login />;
  const nav = (href: string, label: string, active: boolean) => (
    <a href={href} class={active ? "nav-link active" : "nav-link"}>
      {label}
    </a>
  );
  return (
    <div class="shell">
      <header class="topbar">
        <span class="brand">texelbake</span>
        <nav>
          {nav("#/jobs", "Jobs", route.name === "jobs" || route.name === "job")}
          {nav("#/upload", "New bake", route.name === "upload")}
          {nav("#/farm", "Farm", route.name === "farm")}
        </nav>
        <button
          class="btn ghost"
          data-testid="logout"
          onClick={() => {
            setToken(null);
            location.hash = "#/login";
          }}
        >
          Log out
        </button>
      </header>
      <main class="content">
        {route.name === "jobs" && <JobsList />}
        {route.name === "job" && <JobPage id={route.id} tab={route.tab} />}
        {route.name === "upload" && <Upload />}
        {route.name === "farm" && <Farm />}
      </main>
    </div>
  );
}

render(<App />, document.getElementById("app")!);
