"""Surface reflectance fields (seed 002 §3, §5): a reflectance image per (camera, light),
captured from an asset or imported (`capture`, `measured`), kept out of core in a chunked
store of one block per image (`store`, `pca`), rendered on an impostor — the baked enclosing
LOD mesh or the visual hull carved from the captured silhouettes (`hull`) — sampled into
elliptical surfels (`surfels`, `splat`), with unstructured-lumigraph interpolation over
cameras and lights (`ulr`), through deferred, cache-sorted shading operations (`ops`,
`cache`); an environment map as lights (`environment`), a frame (`frame`) and the render
mode of a baked asset (`mode`). Deformation (warps, Table 1, the look-up L) is
`texelbake.deform`'s."""
