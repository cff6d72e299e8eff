"""Per-block PCA compression of one reflectance image (seed 002 §6: the reflectance images
are PCA-compressed at least 10×), with torch.

The image is cut into `tile` × `tile` pixel tiles (edge-replicated to a whole number of
tiles); each tile is a vector of D = tile² · 3 values. The block stores the tiles' mean
(D,), the first k principal directions (k, D) and every tile's k coefficients (T, k): a
pixel decodes as mean + Σ_j coef[t, j] basis[j, d] (a block transform, as KLT image coding).
Stored floats per image: D (k + 1) + T k instead of h w 3 — the ratio grows with the image
(48² and k = 6 on 4² tiles: 5.8×; 256² and k = 8 on 8² tiles: 20×).

Fewer tiles or dimensions than components: k is kept (a fixed block layout) and the
directions beyond rank min(T, D) are zero, so they decode to nothing.
"""

from __future__ import annotations

import numpy as np

from texelbake.errors import SettingsError, ShapeError


def tiles_shape(height: int, width: int, tile: int) -> tuple[int, int]:
    """(tiles down, tiles across) covering an image."""
    return -(-int(height) // int(tile)), -(-int(width) // int(tile))


def block_floats(height: int, width: int, tile: int, components: int) -> int:
    """float32 values of one encoded block (its file's payload)."""
    ty, tx = tiles_shape(height, width, tile)
    d = tile * tile * 3
    return d * (components + 1) + ty * tx * components


def encode(image: np.ndarray, tile: int, components: int) -> np.ndarray:
    """One reflectance image (h, w, 3) → its flat float32 block [mean | basis | coef]."""
    import torch

    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ShapeError(f"image must be (h, w, 3), got {img.shape}")
    if int(tile) < 1 or int(components) < 1:
        raise SettingsError(f"field 'pca': tile and components must be >= 1, got {tile}, "
                            f"{components}")
    h, w, _ = img.shape
    ty, tx = tiles_shape(h, w, tile)
    pad = np.pad(img, ((0, ty * tile - h), (0, tx * tile - w), (0, 0)), mode="edge")
    vec = pad.reshape(ty, tile, tx, tile, 3).transpose(0, 2, 1, 3, 4).reshape(ty * tx, -1)
    mean = vec.mean(axis=0)  # (D,)
    x = torch.as_tensor(vec - mean, dtype=torch.float64)
    _, s, vh = torch.linalg.svd(x, full_matrices=False)
    k = int(components)
    rank = int(min(k, vh.shape[0]))
    basis = np.zeros((k, vec.shape[1]))
    basis[:rank] = vh[:rank].numpy()
    # sign convention: the largest-magnitude entry of each direction is positive (reruns and
    # platforms agree on the bits)
    big = np.argmax(np.abs(basis), axis=1)
    sign = np.where(basis[np.arange(k), big] < 0, -1.0, 1.0)
    basis *= sign[:, None]
    coef = (vec - mean) @ basis.T  # (T, k)
    return np.concatenate([mean, basis.reshape(-1), coef.reshape(-1)]).astype(np.float32)


class PcaBlock:
    """A decoded view of an encoded block: `pixels(ix, iy)` without rebuilding the image."""

    def __init__(self, flat: np.ndarray, height: int, width: int, tile: int,
                 components: int) -> None:
        ty, tx = tiles_shape(height, width, tile)
        d = tile * tile * 3
        k = int(components)
        flat = np.asarray(flat)
        if flat.shape != (block_floats(height, width, tile, k),):
            raise ShapeError(f"PCA block of {height} x {width} (tile {tile}, k {k}) must hold "
                             f"{block_floats(height, width, tile, k)} floats, got {flat.shape}")
        self.mean = flat[:d].astype(np.float64)
        self.basis = flat[d:d + k * d].reshape(k, d).astype(np.float64)
        self.coef = flat[d + k * d:].reshape(ty * tx, k).astype(np.float64)
        self.tile, self.tiles_x, self.k = int(tile), tx, k
        self.nbytes = int(self.mean.nbytes + self.basis.nbytes + self.coef.nbytes)

    def pixels(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        """RGB of pixels (ix, iy) (n,) int → (n, 3) float64. Elementwise (a loop over the k
        components only), so a pixel's value does not depend on which others are decoded."""
        t = self.tile
        tiles = (iy // t) * self.tiles_x + ix // t
        inner = ((iy % t) * t + ix % t) * 3
        out = np.empty((ix.shape[0], 3))
        for ch in range(3):
            d = inner + ch
            acc = self.mean[d].copy()
            for j in range(self.k):  # a loop over the few components
                acc += self.coef[tiles, j] * self.basis[j, d]
            out[:, ch] = acc
        return out


def decode_image(flat: np.ndarray, height: int, width: int, tile: int,
                 components: int) -> np.ndarray:
    """The whole (h, w, 3) float64 image of an encoded block (tests, exports)."""
    blk = PcaBlock(flat, height, width, tile, components)
    iy, ix = np.divmod(np.arange(height * width), width)
    return blk.pixels(ix, iy).reshape(height, width, 3)
