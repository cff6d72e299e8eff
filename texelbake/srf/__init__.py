"""Surface reflectance fields (seed 002 §3, §5): a reflectance image per (camera, light),
captured from an asset or imported (`capture`, `measured`), kept out of core in a chunked
store of one block per image (`store`, `pca`), rendered on an impostor of elliptical surfels
(`surfels`, `splat`) with unstructured-lumigraph interpolation over cameras and lights
(`ulr`) through deferred, cache-sorted shading operations (`ops`, `cache`), and a frame
(`frame`). Deformation (warps, Table 1, the look-up L) is `texelbake.deform`'s."""
