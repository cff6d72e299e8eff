// The dashboard bundle: every library comes from npm (package-lock.json) and is bundled into
// dist/, which the API serves at / (services/main.py). No CDN.
import { defineConfig } from "vite";

export default defineConfig({
  esbuild: { jsx: "automatic", jsxImportSource: "preact" },
  build: { outDir: "dist", emptyOutDir: true, sourcemap: false, target: "es2022" },
  base: "/",
});
