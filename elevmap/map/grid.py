"""Geometry of the robot-centric grid: cells, the moving window and the circular buffer.

All index conventions of the map live here (the drawing is in ``docs/conventions.md``).

Map frame: x forward, y left, z up, metres. Cells lie on a *global lattice* of pitch ``res``: cell
(gx, gy) covers [gx res, (gx + 1) res) x [gy res, (gy + 1) res), gx = floor(x / res). Cell borders
therefore never move when the map moves, and a point on a border belongs to the cell above it.

The map is an n x n *window* of that lattice, lower corner (gx0, gy0): it holds gx0 <= gx < gx0 + n
and gy0 <= gy < gy0 + n; its centre is ((gx0 + n/2) res, (gy0 + n/2) res).

* Map index (i, j) = (gx - gx0, gy - gy0), in [0, n): i grows with x, j grows with y. Layers are
  returned to users in this order (``ElevationMap.layer``): ``layer[i, j]``.
* Buffer index (bi, bj) = (gx mod n, gy mod n): where a cell is stored. Moving the window changes
  (gx0, gy0) only; cells that stay keep their buffer slot (no copy), and the slots of cells that left
  are reused, cleared, by the cells that entered (a two-dimensional circular buffer whose start index
  is (gx0 mod n, gy0 mod n)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .settings import check_coordinates

__all__ = ["GridGeometry"]


@dataclass(frozen=True)
class GridGeometry:
    """An n x n window of the global cell lattice.

    Attributes
    ----------
    n : int
        Cells per side.
    resolution_m : float
        Cell size [m].
    gx0, gy0 : int
        Global index of the window's lower corner cell.
    """

    n: int
    resolution_m: float
    gx0: int = 0
    gy0: int = 0

    @classmethod
    def centred(cls, length_m: float, resolution_m: float, centre_xy=(0.0, 0.0)) -> "GridGeometry":
        """A window of about ``length_m`` [m] per side, centred on ``centre_xy`` (see :meth:`moved_to`)."""
        res = float(resolution_m)
        if not (math.isfinite(res) and res > 0):
            raise ValueError(f"resolution_m must be finite and > 0, got {resolution_m!r}")
        L = float(length_m)
        if not (math.isfinite(L) and L >= res):
            raise ValueError(f"length_m must be finite and >= resolution_m, got {length_m!r}")
        n = int(round(L / res))
        if n > 20000:
            raise ValueError(f"{n} x {n} cells is too large (length_m / resolution_m = {L / res:.0f})")
        g = cls(n, res)
        return g.moved_to(centre_xy)

    @property
    def length_m(self) -> float:
        """Side length of the window [m]."""
        return self.n * self.resolution_m

    @property
    def start_index(self) -> tuple[int, int]:
        """Circular-buffer start: the buffer index of map index (0, 0)."""
        return self.gx0 % self.n, self.gy0 % self.n

    @property
    def centre_xy(self) -> np.ndarray:
        """Centre of the window in the map frame [m]."""
        return np.array([(self.gx0 + self.n / 2) * self.resolution_m, (self.gy0 + self.n / 2) * self.resolution_m])

    @property
    def lower_corner_xy(self) -> np.ndarray:
        """Lower (min x, min y) corner of the window [m]."""
        return np.array([self.gx0 * self.resolution_m, self.gy0 * self.resolution_m])

    def moved_to(self, centre_xy) -> "GridGeometry":
        """The window re-centred on ``centre_xy`` [m] in whole cells.

        With n even the window's centre is the lattice point nearest ``centre_xy``; with n odd it is
        the centre of the cell that contains ``centre_xy``. Either way the robot's cell is one of the
        middle cells, never near an edge.
        """
        try:
            c = np.asarray(centre_xy, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"centre_xy must be 2 finite numbers [m], got {centre_xy!r}") from None
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            raise ValueError(f"centre_xy must be 2 finite numbers [m], got {centre_xy!r}")
        check_coordinates(c, "centre_xy")
        res = self.resolution_m
        half = self.n // 2
        offset = 0.5 if self.n % 2 == 0 else 0.0
        gx0 = int(math.floor(c[0] / res + offset)) - half
        gy0 = int(math.floor(c[1] / res + offset)) - half
        return GridGeometry(self.n, res, gx0, gy0)

    # -- positions and indices -------------------------------------------------------------------
    def global_index(self, xy) -> np.ndarray:
        """Global lattice index floor(xy / res), int64, shape (..., 2)."""
        return np.floor(np.asarray(xy, dtype=np.float64) / self.resolution_m).astype(np.int64)

    def map_index(self, xy):
        """Map index (i, j) of positions, shape (..., 2), and a mask of those inside the window."""
        g = self.global_index(xy)
        ij = g - np.array([self.gx0, self.gy0])
        inside = np.all((ij >= 0) & (ij < self.n), axis=-1)
        return ij, inside

    def buffer_index(self, map_ij) -> np.ndarray:
        """Buffer index of map indices (..., 2)."""
        ij = np.asarray(map_ij, dtype=np.int64)
        return (ij + np.array([self.gx0, self.gy0])) % self.n

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """x [m] of map rows i and y [m] of map columns j (cell centres), each shape (n,)."""
        k = np.arange(self.n)
        res = self.resolution_m
        return (self.gx0 + k + 0.5) * res, (self.gy0 + k + 0.5) * res

    def unwrap(self, buffer_array: np.ndarray) -> np.ndarray:
        """A buffer-ordered array (..., n, n) as a new array in map-index order."""
        sx, sy = self.start_index
        return np.roll(buffer_array, shift=(-sx, -sy), axis=(-2, -1))

    def wrap(self, map_array: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`unwrap`."""
        sx, sy = self.start_index
        return np.roll(map_array, shift=(sx, sy), axis=(-2, -1))

    def uncovered_by_move(self, new: "GridGeometry") -> tuple[np.ndarray, np.ndarray]:
        """Buffer rows and columns whose cells are new in ``new`` (they must be cleared).

        Returns (rows, cols): buffer rows bi whose global x index entered the window, and buffer
        columns bj likewise for y. A shift of n or more cells renews everything.
        """
        if new.n != self.n or new.resolution_m != self.resolution_m:
            raise ValueError("windows of different size or resolution")
        return _entered(self.gx0, new.gx0, self.n), _entered(self.gy0, new.gy0, self.n)


def _entered(old0: int, new0: int, n: int) -> np.ndarray:
    """Buffer slots (mod n) of global indices in [new0, new0 + n) but not in [old0, old0 + n)."""
    shift = new0 - old0
    if abs(shift) >= n:
        return np.arange(n)
    if shift > 0:
        g = np.arange(old0 + n, new0 + n)
    else:
        g = np.arange(new0, old0)
    return np.sort(g % n)
