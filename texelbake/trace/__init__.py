"""Tracing M_org, below both the renderer (`texelbake.render`) and the reflectance field
(`texelbake.srf`): pinhole cameras and eye rays, the wavefront loop, direct light with shadow
rays, and M_org ready to trace with its ground truth (`org`)."""
