"""Surface materials of the virtual FPP sensor: the albedo at any hit point of a mesh.

* :class:`ProceduralMaterial`: a solid 3D texture (fractal value noise, sharpened into blobs),
  evaluated at the 3D hit point, so any mesh gets texture without UVs;
* :class:`VertexColorMaterial`: the mesh's vertex colours, interpolated barycentrically;
* :class:`ImageMaterial`: an image mapped through per-corner UVs (posters).

Every material answers ``albedo(points_world, triangle_ids, bary_uv)``: the albedo in [0, 1] at
hit points (N, 3) on triangles (N,) with barycentrics (N, 2).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial.transform import Rotation

_LATTICE = 1024  # noise tile size in cells; the texture repeats every 256 * scale_m
_NOISE_CACHE: dict[int, list[NDArray[np.float32]]] = {}
_NOISE_LOCK = threading.Lock()


def _noise_planes(seed: int) -> list[NDArray[np.float32]]:
    """Three smooth, zero-mean, unit-std 2D noise tiles (one per coordinate plane) for a seed."""
    with _NOISE_LOCK:
        if seed not in _NOISE_CACHE:
            rng = np.random.default_rng(seed)
            tiles = []
            for _ in range(3):
                tile = ndimage.gaussian_filter(rng.standard_normal((_LATTICE, _LATTICE), dtype=np.float32), 1.5, mode="wrap")
                tiles.append((tile - tile.mean()) / tile.std())
            _NOISE_CACHE[seed] = tiles
        return _NOISE_CACHE[seed]


_TEXTURE_ROTATION = Rotation.from_euler("xyz", [37.0, 23.0, 61.0], degrees=True).as_matrix()
_ROW = 1024  # cv2.remap maps must stay below 32767 in each dimension: sample in rows of this width


def _sample_tile(tile: NDArray[np.float32], cols: NDArray[np.float32], rows: NDArray[np.float32]) -> NDArray[np.float32]:
    """Bilinear samples of a wrapping tile at (cols, rows), both (h * _ROW,) float32 contiguous.

    cv2.remap converts coordinates to fixed point (|coordinate| < 32767 cells) and wraps them
    with BORDER_WRAP; it runs at memory speed.
    """
    h = cols.size // _ROW
    return cv2.remap(tile, cols.reshape(h, _ROW), rows.reshape(h, _ROW), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).reshape(-1)


@dataclass(frozen=True)
class ProceduralMaterial:
    """Solid texture: ``base + contrast/2 * tanh(sharpness * fbm(p / scale) / 2)`` clipped to [0, 1].

    ``fbm`` is ``octaves`` of smooth noise, each octave half the scale of the previous, so
    features span ``scale_m / 2**(octaves-1)`` to ``scale_m``. Each octave is the sum of three 2D
    noise tiles evaluated on the point's (y, z), (z, x) and (x, y) coordinates: a function of
    the 3D position (a solid texture, no UVs needed) that runs at image-filtering speed.
    ``stripes_m`` > 0 adds a wood-like stripe modulation along x (doors).
    """

    base: float = 0.55
    contrast: float = 0.6
    scale_m: float = 0.03
    octaves: int = 3
    sharpness: float = 3.0
    seed: int = 0
    stripes_m: float = 0.0

    def albedo(self, points_world: NDArray, triangle_ids: NDArray | None = None, bary_uv: NDArray | None = None) -> NDArray[np.float64]:
        # A generic rotation first: axis-aligned walls would otherwise see two of the three 2D
        # tiles as 1D stripes (a plaid look that gives poorly localised keypoints).
        p0 = np.asarray(points_world)
        p = p0 @ _TEXTURE_ROTATION.T.astype(p0.dtype)
        n = p.shape[0]
        tiles = _noise_planes(self.seed)
        padded = -(-n // _ROW) * _ROW
        coords = np.zeros((3, padded), dtype=np.float32)
        total = np.zeros(padded, dtype=np.float32)
        weight_sum = 0.0
        cells_per_scale = 4.0  # lattice cells per feature size (the tile is blurred over 1.5 cells)
        for k in range(max(1, self.octaves)):
            f = cells_per_scale * (2.0**k) / self.scale_m
            for a in range(3):
                # Fold large coordinates into one tile period in float64 first, so the float32
                # coordinates cv2.remap sees stay small and exact to ~1e-4 cell.
                np.mod(p[:, a] * f + 97.3 * (k + 1), _LATTICE, out=coords[a, :n], casting="unsafe")
            w = 0.55**k
            octave = _sample_tile(tiles[0], coords[1], coords[2])
            octave += _sample_tile(tiles[1], coords[2], coords[0])
            octave += _sample_tile(tiles[2], coords[0], coords[1])
            octave *= np.float32(w / math.sqrt(3.0))
            total += octave
            weight_sum += w * w
        total = total[:n]
        fbm = total / np.float32(math.sqrt(weight_sum))  # ~unit standard deviation
        if self.stripes_m > 0:
            fbm = 0.6 * fbm + 0.4 * np.sin(2 * np.pi * p0[:, 0] / self.stripes_m + 2.0 * fbm)
        a = self.base + 0.5 * self.contrast * np.tanh(self.sharpness * fbm / 2.0)
        return np.clip(a, 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class VertexColorMaterial:
    """Albedo from per-vertex grey values (luminance of vertex colours), interpolated."""

    vertex_albedo: NDArray[np.float64]
    triangles: NDArray[np.int64]

    def albedo(self, points_world: NDArray, triangle_ids: NDArray, bary_uv: NDArray) -> NDArray[np.float64]:
        tri = self.triangles[triangle_ids]
        a = self.vertex_albedo
        u, v = bary_uv[:, 0], bary_uv[:, 1]
        return (1 - u - v) * a[tri[:, 0]] + u * a[tri[:, 1]] + v * a[tri[:, 2]]


@dataclass(frozen=True, eq=False)
class ImageMaterial:
    """Albedo from a grey image (h, w) in [0, 1] through per-corner UVs (T, 3, 2) in [0, 1].

    UV (0, 0) is the image's top-left corner, u along columns, v along rows.
    """

    image: NDArray[np.float32]
    triangle_uvs: NDArray[np.float64]

    def albedo(self, points_world: NDArray, triangle_ids: NDArray, bary_uv: NDArray) -> NDArray[np.float64]:
        uv = self.triangle_uvs[triangle_ids]
        b1, b2 = bary_uv[:, :1], bary_uv[:, 1:2]
        tex = (1 - b1 - b2) * uv[:, 0] + b1 * uv[:, 1] + b2 * uv[:, 2]
        h, w = self.image.shape
        cols = tex[:, 0] * w - 0.5
        rows = tex[:, 1] * h - 0.5
        return ndimage.map_coordinates(self.image, [rows, cols], order=1, mode="nearest").astype(np.float64)
