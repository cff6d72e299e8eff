"""The chunked on-disk store of a surface reflectance field: one block per reflectance image
(camera c, light l), each a NumPy `.npy` file, and `srf.json` (cameras, light directions,
encoding). Reading one block is the unit of I/O; the field is never loaded whole
(docs/decisions.md: why `.npy` blocks rather than zarr or tiled EXR).

Layout of a store folder:

    srf.json                       format, size, encoding, cameras, light directions, stats
    blocks/c0000_l000.npy          raw: (h, w, 3) float32 linear reflectance
                                   pca: flat float32 [mean | basis | coef] (`srf.pca`)

A reflectance value is the radiance the camera saw under a directional light of unit
irradiance: under a light of irradiance E (or a point light, Eq. 11) radiance = SRF · E.
Blocks are written atomically and deterministically (np.save of a fixed dtype and shape,
JSON with sorted keys), so a rerun of a capture is byte-identical.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from texelbake.errors import AssetError, SettingsError, ShapeError
from texelbake.io.atomic import atomic_path
from texelbake.srf import pca
from texelbake.srf.rig import camera_from_json, camera_to_json
from texelbake.trace.camera import PinholeCamera

FORMAT = "texelbake-srf"
VERSION = 1
ENCODINGS = ("raw", "pca")


def block_file(root: Path, camera: int, light: int) -> Path:
    """The file of block (camera, light) in a store folder."""
    return Path(root) / "blocks" / f"c{int(camera):04d}_l{int(light):03d}.npy"


class RawBlock:
    """A raw reflectance image in memory: `pixels(ix, iy)`."""

    def __init__(self, image: np.ndarray) -> None:
        self.image = image
        self.nbytes = int(image.nbytes)

    def pixels(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        return self.image[iy, ix].astype(np.float64)


def sample_bilinear(block: RawBlock | pca.PcaBlock, x: np.ndarray, y: np.ndarray,
                    width: int, height: int) -> np.ndarray:
    """Bilinear look-up at continuous pixel coordinates (pixel centres at i + 0.5, edges
    clamped). x, y : (n,) float64 → (n, 3) float64; each result depends on its own (x, y)
    only (bitwise, whatever else is looked up in the same call)."""
    fx = np.asarray(x, dtype=np.float64) - 0.5
    fy = np.asarray(y, dtype=np.float64) - 0.5
    x0, y0 = np.floor(fx), np.floor(fy)
    wx, wy = (fx - x0)[:, None], (fy - y0)[:, None]
    x0i, y0i = x0.astype(np.int64), y0.astype(np.int64)
    xa, xb = np.clip(x0i, 0, width - 1), np.clip(x0i + 1, 0, width - 1)
    ya, yb = np.clip(y0i, 0, height - 1), np.clip(y0i + 1, 0, height - 1)
    top = (1.0 - wx) * block.pixels(xa, ya) + wx * block.pixels(xb, ya)
    bottom = (1.0 - wx) * block.pixels(xa, yb) + wx * block.pixels(xb, yb)
    return (1.0 - wy) * top + wy * bottom


@dataclass
class SrfStore:
    """An opened store (`open_store`): metadata in memory, blocks on disk."""

    path: Path
    cameras: list[PinholeCamera]
    light_dirs: np.ndarray  # (m, 3) float64 unit, toward the light
    width: int
    height: int
    encoding: str
    tile: int
    components: int
    meta: dict[str, Any]

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    @property
    def n_lights(self) -> int:
        return int(self.light_dirs.shape[0])

    @property
    def camera_positions(self) -> np.ndarray:
        """(c, 3) float64"""
        return np.stack([c.position for c in self.cameras])

    def block_path(self, camera: int, light: int) -> Path:
        return block_file(self.path, camera, light)

    def block_nbytes(self) -> int:
        """Bytes of one block as held in memory (float64 decoded arrays for pca)."""
        if self.encoding == "raw":
            return self.width * self.height * 3 * 4
        return pca.block_floats(self.height, self.width, self.tile, self.components) * 8

    def read_block(self, camera: int, light: int) -> RawBlock | pca.PcaBlock:
        """Read one reflectance image from disk (the unit of I/O)."""
        p = self.block_path(camera, light)
        try:
            arr = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise AssetError(f"cannot read reflectance block ({e})", path=str(p)) from None
        if self.encoding == "raw":
            if arr.shape != (self.height, self.width, 3):
                raise AssetError(f"block must be ({self.height}, {self.width}, 3), got "
                                 f"{arr.shape}", path=str(p))
            return RawBlock(arr)
        try:
            return pca.PcaBlock(arr, self.height, self.width, self.tile, self.components)
        except ShapeError as e:
            raise AssetError(str(e), path=str(p)) from None

    def silhouette(self, camera: int) -> np.ndarray:
        """(h, w) float32 fraction of each pixel the object covers, seen by `camera`
        (`silhouettes/c0000.npy`; written by captures and by imports given masks).
        AssetError naming the file when the store has none."""
        p = self.path / "silhouettes" / f"c{int(camera):04d}.npy"
        try:
            sil = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise AssetError(f"no silhouette ({e})", path=str(p)) from None
        if sil.shape != (self.height, self.width):
            raise AssetError(f"silhouette must be ({self.height}, {self.width}), got "
                             f"{sil.shape}", path=str(p))
        return sil

    def image(self, camera: int, light: int) -> np.ndarray:
        """The whole (h, w, 3) float64 reflectance image of one block (tests, previews)."""
        blk = self.read_block(camera, light)
        iy, ix = np.divmod(np.arange(self.height * self.width), self.width)
        return blk.pixels(ix, iy).reshape(self.height, self.width, 3)


class SrfWriter:
    """Writes a store block by block (`write`), then `srf.json` (`close`)."""

    def __init__(self, path: str | Path, cameras: list[PinholeCamera], light_dirs: object, *,
                 encoding: str = "raw", tile: int = 4, components: int = 6,
                 source: str = "") -> None:
        if encoding not in ENCODINGS:
            raise SettingsError(f"field 'encoding': expected one of {ENCODINGS}, got "
                                f"{encoding!r}")
        if not cameras:
            raise SettingsError("field 'cameras': a reflectance field needs a camera")
        sizes = {(c.width, c.height) for c in cameras}
        if len(sizes) != 1:
            raise SettingsError(f"field 'cameras': every camera must have one image size, got "
                                f"{sorted(sizes)}")
        dirs = np.asarray(light_dirs, dtype=np.float64)
        if dirs.ndim != 2 or dirs.shape[1] != 3 or dirs.shape[0] < 1:
            raise ShapeError(f"light directions must be (m >= 1, 3), got {dirs.shape}")
        ln = np.linalg.norm(dirs, axis=1, keepdims=True)
        if not (np.isfinite(dirs).all() and np.all(ln > 0)):
            raise SettingsError("field 'lights': light directions must be finite and non-zero")
        self.path = Path(path)
        self.cameras = list(cameras)
        self.light_dirs = dirs / ln
        (self.width, self.height), = sizes
        self.encoding, self.tile, self.components = encoding, int(tile), int(components)
        self.source = source
        self._written: set[tuple[int, int]] = set()
        self._sq_err = 0.0
        self._sq_ref = 0.0
        self._peak = 0.0

    def write(self, camera: int, light: int, image: object) -> Path:
        """Encode and write one reflectance image (h, w, 3) linear, atomically."""
        img = np.asarray(image, dtype=np.float32)
        if img.shape != (self.height, self.width, 3):
            raise ShapeError(f"reflectance image (camera {camera}, light {light}) must be "
                             f"({self.height}, {self.width}, 3), got {img.shape}")
        if not np.isfinite(img).all():
            raise AssetError(f"reflectance image (camera {camera}, light {light}) has NaN or "
                             f"Inf pixels")
        if not (0 <= camera < len(self.cameras) and 0 <= light < len(self.light_dirs)):
            raise SettingsError(f"block ({camera}, {light}) outside {len(self.cameras)} "
                                f"cameras x {len(self.light_dirs)} lights")
        if self.encoding == "pca":
            data = pca.encode(img, self.tile, self.components)
            dec = pca.decode_image(data, self.height, self.width, self.tile, self.components)
            self._sq_err += float(np.sum((dec - img) ** 2))
        else:
            data = img
        self._sq_ref += float(np.sum(img.astype(np.float64) ** 2))
        self._peak = max(self._peak, float(img.max(initial=0.0)))
        target = block_file(self.path, camera, light)
        with atomic_path(target) as tmp, open(tmp, "wb") as fh:
            np.save(fh, np.ascontiguousarray(data), allow_pickle=False)
        self._written.add((int(camera), int(light)))
        return target

    def write_silhouette(self, camera: int, coverage: object) -> Path:
        """The object's coverage (h, w) in [0, 1] seen by one camera (for the visual hull)."""
        cov = np.asarray(coverage, dtype=np.float32)
        if cov.shape != (self.height, self.width) or not np.isfinite(cov).all():
            raise ShapeError(f"silhouette of camera {camera} must be finite "
                             f"({self.height}, {self.width}), got {cov.shape}")
        target = self.path / "silhouettes" / f"c{int(camera):04d}.npy"
        with atomic_path(target) as tmp, open(tmp, "wb") as fh:
            np.save(fh, np.clip(cov, 0.0, 1.0), allow_pickle=False)
        return target

    def close(self, extra: dict[str, Any] | None = None) -> SrfStore:
        """Check every block was written, write `srf.json`, return the opened store."""
        grid = [(c, lt) for c in range(len(self.cameras)) for lt in range(len(self.light_dirs))]
        # blocks written by this writer or already on disk (other shards of a capture)
        missing = [k for k in grid
                   if k not in self._written and not block_file(self.path, *k).is_file()]
        if missing:
            raise SettingsError(f"store {self.path}: {len(missing)} blocks not written, first "
                                f"(camera, light) = {missing[0]}")
        raw_floats = self.width * self.height * 3
        stored = (raw_floats if self.encoding == "raw"
                  else pca.block_floats(self.height, self.width, self.tile, self.components))
        stats: dict[str, Any] = {"compression_ratio": raw_floats / stored}
        if self.encoding == "pca" and len(self._written) == len(grid):  # all seen here
            stats["pca_snr_db"] = (math.inf if self._sq_err == 0 else
                                   10.0 * math.log10(max(self._sq_ref, 1e-300) / self._sq_err))
        meta = {"format": FORMAT, "version": VERSION, "width": self.width,
                "height": self.height, "encoding": self.encoding, "tile": self.tile,
                "components": self.components, "source": self.source,
                "cameras": [camera_to_json(c) for c in self.cameras],
                "lights": [[float(x) for x in d] for d in self.light_dirs],
                "stats": {k: (str(v) if isinstance(v, float) and not math.isfinite(v) else v)
                          for k, v in stats.items()},
                **(extra or {})}
        with atomic_path(self.path / "srf.json") as tmp:
            tmp.write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
        return open_store(self.path)


def subset(store: SrfStore, cameras: list[int], lights: list[int], out: str | Path
           ) -> SrfStore:
    """A store of some of `store`'s cameras and lights (renumbered in the given order), its
    blocks copied file by file (a sweep over rig sizes, a shard of a rig)."""
    w = SrfWriter(out, [store.cameras[c] for c in cameras], store.light_dirs[list(lights)],
                  encoding=store.encoding, tile=store.tile, components=store.components,
                  source=str(store.path))
    for i, c in enumerate(cameras):  # a loop over files
        for k, j in enumerate(lights):
            with atomic_path(block_file(w.path, i, k)) as tmp:
                tmp.write_bytes(store.block_path(c, j).read_bytes())
            w._written.add((i, k))
    return w.close({"stats": store.meta.get("stats", {}),
                    "subset_of": {"store": str(store.path), "cameras": list(map(int, cameras)),
                                  "lights": list(map(int, lights))}})


def open_store(path: str | Path) -> SrfStore:
    """Open a store folder (reads `srf.json` only). AssetError naming the file when it is
    missing or malformed."""
    root = Path(path)
    mfile = root / "srf.json"
    if not mfile.is_file():
        raise AssetError("not a reflectance-field store (no srf.json)", path=str(root))
    try:
        meta = json.loads(mfile.read_text())
    except (OSError, ValueError) as e:
        raise AssetError(f"cannot read ({e})", path=str(mfile)) from None
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise AssetError(f"expected format {FORMAT} version {VERSION}, got "
                         f"{meta.get('format')!r} {meta.get('version')!r}", path=str(mfile))
    try:
        cams = [camera_from_json(c, f"{mfile}: cameras[{i}]")
                for i, c in enumerate(meta["cameras"])]
        dirs = np.asarray(meta["lights"], dtype=np.float64).reshape(-1, 3)
        enc = str(meta["encoding"])
        w, h = int(meta["width"]), int(meta["height"])
    except (KeyError, TypeError, ValueError, SettingsError) as e:
        raise AssetError(f"malformed store metadata ({e})", path=str(mfile)) from None
    if enc not in ENCODINGS:
        raise AssetError(f"field 'encoding' must be one of {ENCODINGS}, got {enc!r}",
                         path=str(mfile))
    return SrfStore(root, cams, dirs, w, h, enc, int(meta.get("tile", 1)),
                    int(meta.get("components", 0)), meta)
