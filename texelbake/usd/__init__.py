"""The baked USD: the asset as arrays (`baked`), writing it (`write`), reading it back
(`read`, the renderer's only way in), packing it (`package`), and its parts: LOD meshes,
variants and proxy, the UsdPreviewSurface fallback, texelbake's shader definitions, and one
LOD exported as a self-contained file (`export`)."""
