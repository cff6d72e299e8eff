"""The `srf` render mode of a baked asset (`texelbake render BAKED --modes srf`, and under a
warp `srf` / `srf-naive`): the reflectance field captured beside the baked USD (`srf/`, as
the BTF maps are; `capture_beside`) rendered on surfels of the baked enclosing LOD mesh M1
(`surfels.surfels_from_baked`; `impostor="hull"`: of the visual hull carved from the
captured silhouettes, `hull.visual_hull`) under the scene's lights (`frame.render_srf`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from texelbake.deform.warps import Warp
from texelbake.errors import SettingsError, StageError
from texelbake.srf.cache import DEFAULT_CAPACITY
from texelbake.srf.capture import capture
from texelbake.srf.deferred import render_srf
from texelbake.srf.hull import visual_hull
from texelbake.srf.store import SrfStore, open_store
from texelbake.srf.surfels import Surfels, surfels_from_baked, surfels_from_mesh
from texelbake.trace.camera import PinholeCamera

#: the store's folder beside the baked USD
STORE_DIR = "srf"


def default_store_path(scene: Any) -> Path:
    """`<folder of the baked USD>/srf`."""
    root = getattr(scene, "root", None)
    if root is None:
        raise StageError("mode 'srf' needs a baked asset (RenderScene) or an explicit store "
                         "(srf=PATH)")
    return Path(root).parent / STORE_DIR


def capture_beside(scene: Any, **kw: Any) -> SrfStore:
    """Capture the scene's M_org (`capture.capture`, keywords passed on) into
    `default_store_path(scene)`."""
    return capture(scene.asset, default_store_path(scene), **kw)


IMPOSTORS = ("lod", "hull")


def scene_surfels(scene: Any, lod: int = 1, spacing: float | None = None,
                  impostor: str = "lod", store: SrfStore | None = None) -> Surfels:
    """Surfels of the scene's M_lod (or of the store's visual hull), built once per scene
    and (impostor, lod, spacing, store)."""
    if impostor not in IMPOSTORS:
        raise SettingsError(f"field 'impostor': expected one of {IMPOSTORS}, got {impostor!r}")
    cache = scene.__dict__.setdefault("_srf_surfels", {})
    key = (impostor, int(lod), spacing, str(store.path) if store is not None else "")
    if key not in cache:
        if impostor == "hull":
            if store is None:
                raise SettingsError("field 'impostor': 'hull' needs the field's store")
            cache[key] = surfels_from_mesh(*visual_hull(store), spacing)
        else:
            cache[key] = surfels_from_baked(scene, lod, spacing)
    return cache[key]


def render_srf_mode(scene: Any, cam: PinholeCamera, *, srf: str | Path | SrfStore | None = None,
                    warp: Warp | None = None, use_lookup: bool = True, lod: int = 1,
                    spacing: float | None = None, executor: str = "sorted",
                    cache_blocks: int = DEFAULT_CAPACITY, circular: bool = False,
                    impostor: str = "lod", **_: Any) -> tuple[np.ndarray, int, np.ndarray, dict[str, Any]]:
    """`render_frame`'s contract: (image (h, w, 3), rays, coverage (h, w), extras).
    scene : the rest RenderScene (its M1, lights); warp : Ψ for a deformed frame."""
    if isinstance(srf, SrfStore):
        store = srf
    else:
        path = Path(srf) if srf is not None else default_store_path(scene)
        if not (path / "srf.json").is_file():
            raise StageError(f"mode 'srf': no reflectance field at {path}; capture one with "
                             f"`texelbake srf-capture BAKED` (or pass srf=PATH)")
        store = open_store(path)
    surf = scene_surfels(scene, lod, spacing, impostor, store)
    res = render_srf(store, surf, cam, scene.lights, warp=warp,
                     use_lookup=use_lookup, executor=executor, cache_blocks=cache_blocks,
                     circular=circular)
    return res.image, res.rays_cast, res.coverage, res.extras  # type: ignore[return-value]
