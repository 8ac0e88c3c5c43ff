"""The grid the inversions run on: soil cells, slip nodes, and the whitened feature tables (pure computation).

* :class:`SoilGrid`: cells of ``(kS, phiS, dphi)`` [N/m, rad, rad] on level
  axes, those with ``phiD = phiS - dphi >= phid_min``;
* :data:`SLIP_NODES`, :func:`slip_prior`: the slip nodes [-] and their log prior;
* :class:`GridTables`: for one :class:`~slipest.inverse.surrogate.FeatureSurrogate`,
  the mean features of every cell at every slip node, whitened by the
  model's covariance, for a leg speed and a smoothed noise level, as
  columnar ``(D, K, S)`` tables of int16 counts of a step per coordinate
  (coordinate, slip node, cell: the layout of
  :mod:`slipest.inverse.grid_kernels`). The speed and the noise
  are binned (1 % and 5 % steps) and a few tables are kept, so a run at a
  steady speed builds one table (about 40 ms) and a run whose speed
  changes builds one per change; one set of tables serves every wheel
  using the same model and grid (:func:`grid_tables`).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from slipest.inverse.grid_kernels import quantise_into, quantise_product_into
from slipest.inverse.surrogate import whitener

#: Slip nodes of the grid inversions [-]: 0 to 0.55 by 0.01.
SLIP_NODES = np.round(np.arange(0.0, 0.5501, 0.01), 6)


def slip_prior(nodes, hi: float = 0.5, tail: float = 4.0) -> np.ndarray:
    """Log prior over slip nodes: flat on ``[0, hi]``, ``-tail`` above (the estimator's range is 0-0.5)."""
    nodes = np.asarray(nodes, dtype=float)
    return np.where(nodes <= hi + 1e-9, 0.0, -float(tail))


@dataclass(frozen=True)
class SoilGrid:
    """Soil cells: levels of kS [N/m], phiS [rad], dphi [rad]; the cells with ``phiS - dphi >= phid_min`` [rad]."""

    kS: np.ndarray
    phiS: np.ndarray
    dphi: np.ndarray
    phid_min: float = 0.1

    @classmethod
    def default(cls) -> "SoilGrid":
        """11 x 24 x 31 levels: kS 500-1500 N/m (100 apart), phiS 0.10-0.867 rad (1/30 apart), dphi 0-0.35 rad
        (0.0117 apart), ``phiD >= 0.10`` rad: 6226 cells. The ``dphi`` axis is the finest: one cycle pins the
        oscillation amplitude, which ``dphi`` sets, more sharply than ``kS`` or ``phiS`` (docs/estimator.md)."""
        return cls(np.linspace(500.0, 1500.0, 11), 0.1 + np.arange(24) / 30.0, np.linspace(0.0, 0.35, 31), 0.1)

    def refined(self, n: int) -> "SoilGrid":
        """The same ranges with every axis's spacing divided by ``n`` (an integer >= 1; the levels include
        these ones): about ``n**3`` times the cells, and as many times the estimator's work per cycle."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"grid refinement must be an integer >= 1, got {n!r}")
        n = int(n)

        def axis(v):
            return np.linspace(v[0], v[-1], (v.size - 1) * n + 1) if v.size > 1 else v.copy()

        return SoilGrid(axis(self.kS), axis(self.phiS), axis(self.dphi), self.phid_min)

    @property
    def mask(self) -> np.ndarray:
        """``(nk, nphiS, ndphi)`` True where the cell exists (``phiS - dphi >= phid_min``)."""
        valid = self.phiS[:, None] - self.dphi[None, :] >= self.phid_min - 1e-9
        return np.broadcast_to(valid[None], (self.kS.size,) + valid.shape)

    @property
    def size(self) -> int:
        return int(self.mask.sum())

    def cells(self) -> np.ndarray:
        """``(S, 3)``: kS [N/m], phiS, phiD [rad] of every cell (C order over the levels)."""
        k, p, d = np.meshgrid(self.kS, self.phiS, self.dphi, indexing="ij")
        m = self.mask
        return np.column_stack([k[m], p[m], (p - d)[m]])

    def steps(self) -> np.ndarray:
        """Level spacing of (kS, phiS, dphi)."""
        return np.array([np.ptp(v) / max(v.size - 1, 1) for v in (self.kS, self.phiS, self.dphi)])

    def key(self) -> tuple:
        return (self.kS.tobytes(), self.phiS.tobytes(), self.dphi.tobytes(), self.phid_min)

    def outside(self, kS=None, phiS=None, phiD=None, dphi=None) -> str | None:
        """What of a (partly) known soil lies outside the grid's ranges (kS [N/m], angles [rad]), as
        ``"kS=3000 N/m (covered: 500-1500)"``; None when every part given lies within them."""
        spans = {"kS": (kS, self.kS, " N/m"), "phiS": (phiS, self.phiS, " rad"), "dphi": (dphi, self.dphi, " rad"),
                 "phiD": (phiD, np.array([self.phid_min, self.phiS.max()]), " rad")}
        out = [f"{name}={v:g}{unit} (covered: {levels.min():.4g}-{levels.max():.4g})"
               for name, (v, levels, unit) in spans.items()
               if v is not None and not levels.min() - 1e-9 <= v <= levels.max() + 1e-9]
        return ", ".join(out) or None


@dataclass(frozen=True)
class Table:
    """One whitened table: ``columnar`` ``(D, K, S)`` int16 (``D`` the modelled features; each coordinate is
    read once per cycle, so the table holds no padding) and ``step`` ``(D,)`` float32, the table's values
    being ``columnar * step[:, None, None]`` (within ``step / 2``, at most 6e-3 of a standard deviation, up
    to :data:`QUANTISE_LIMIT`: see :func:`quantise`); ``whitener`` ``(D, D)`` (features minus the table's
    values, times it, are standard normal in every coordinate), and the binned leg speed [rad/s] and
    smoothed noise [g] it is for."""

    columnar: np.ndarray
    step: np.ndarray
    whitener: np.ndarray
    omega: float
    noise_smooth: float

    def values(self) -> np.ndarray:
        """The table's values, ``(D, K, S)`` float32 (a copy: for checks, not for the kernels)."""
        return self.columnar * self.step[:, None, None]


#: Largest whitened mean a table holds [standard deviations]: beyond it a value is clipped (a cell that far
#: from a cycle has no weight either way; clipped, it cannot coarsen the step of every other cell).
QUANTISE_LIMIT = 400.0


def quantise(values: np.ndarray, limit: float = QUANTISE_LIMIT) -> tuple[np.ndarray, np.ndarray]:
    """``values`` ``(D, K, S)`` (whitened: standard deviations) as int16 counts of a step per coordinate:
    ``(counts, step)``, ``step`` ``(D,)`` float32 the largest ``|value|`` of the coordinate, at most ``limit``,
    over 32767. Each value within ``+-limit`` is held within ``step / 2`` (at most 6e-3 of a standard
    deviation); one beyond is clipped to ``+-limit``. The shipped model's whitened means reach 50-200, so
    none is clipped and a squared distance near the best cells moves by < 0.1. The table is half the size
    of float32's, and reading it is what the distances cost (docs/estimator.md, "Speed")."""
    values = np.asarray(values, dtype=np.float64)
    counts = np.empty(values.shape, dtype=np.int16)
    step = np.empty(values.shape[0], dtype=np.float32)
    quantise_into(values, float(limit), counts, step)
    return counts, step


def quantise_product(partial: np.ndarray, basis: np.ndarray, cells: np.ndarray,
                     limit: float = QUANTISE_LIMIT) -> tuple[np.ndarray, np.ndarray]:
    """:func:`quantise` of the table ``values[d, k, s] = sum_a basis[k, a] * partial[a, d, cells[s]]`` without
    making it: ``partial`` ``(A, D, G)`` (a grid's factors, :meth:`FeatureSurrogate.grid_factors`, its grid
    flattened), ``basis`` ``(K, A)``, ``cells`` ``(S,)`` indices into the flattened grid. The same counts
    and steps as :func:`quantise` of the contracted grid, to the rounding of the sums (a count one off
    where a value lies within 1e-12 of a half step). A table build then reads the factors (the
    shipped model's: 20 MB in float64) instead of writing a 37 MB grid and reading it twice, and takes
    half the time (docs/estimator.md, "Speed")."""
    partial = np.ascontiguousarray(partial, dtype=np.float64)
    basis_t = np.ascontiguousarray(np.asarray(basis, dtype=np.float64).T)
    cells = np.ascontiguousarray(cells, dtype=np.int64)
    if partial.ndim != 3 or basis_t.shape[0] != partial.shape[0] or cells.ndim != 1:
        raise ValueError(f"partial (A, D, G), basis (K, A) and cells (S,) expected, got {partial.shape}, "
                         f"{np.shape(basis)}, {cells.shape}")
    if cells.size and (cells.min() < 0 or cells.max() >= partial.shape[2]):
        raise ValueError(f"cells must index the grid's {partial.shape[2]} points")
    D, K = partial.shape[1], basis_t.shape[1]
    counts = np.empty((D, K, cells.size), dtype=np.int16)
    step = np.empty(D, dtype=np.float32)
    quantise_product_into(partial, basis_t, cells, float(limit), counts, step, np.empty((cells.size, K)))
    return counts, step


#: Relative width of the leg-speed and smoothed-noise bins of the tables [-].
OMEGA_STEP = 0.01
NOISE_STEP = 0.05
#: Smallest smoothed noise a table is built for [g] (below it, the model's noise-free figures).
NOISE_FLOOR = 2e-4


class GridTables:
    """Whitened tables of one model on one grid and slip nodes, per (leg speed, noise) bin (see the module docstring).

    ``max_tables``: how many are kept (least recently used goes first).
    """

    def __init__(self, model, grid: SoilGrid, nodes=SLIP_NODES, max_tables: int = 8):
        self.model = model
        self.grid = grid
        self.nodes = np.asarray(nodes, dtype=float)
        self.max_tables = int(max_tables)
        self._tables: OrderedDict = OrderedDict()
        self._cells = np.flatnonzero(grid.mask.reshape(-1))  # the cells in the flattened tensor grid
        self.builds = 0

    @staticmethod
    def bin_of(omega: float, noise_smooth: float) -> tuple[int, int]:
        """The bin of a leg speed [rad/s] and a smoothed noise [g] (log-spaced)."""
        return (int(round(math.log(omega) / math.log1p(OMEGA_STEP))),
                int(round(math.log(max(noise_smooth, NOISE_FLOOR)) / math.log1p(NOISE_STEP))))

    def get(self, omega: float, noise_smooth: float) -> Table:
        """The table of the bin holding ``omega`` [rad/s] and ``noise_smooth`` [g] (built on first use)."""
        key = self.bin_of(omega, noise_smooth)
        table = self._tables.get(key)
        if table is None:
            table = self._build(math.exp(key[0] * math.log1p(OMEGA_STEP)), math.exp(key[1] * math.log1p(NOISE_STEP)))
            self._tables[key] = table
            if len(self._tables) > self.max_tables:
                self._tables.popitem(last=False)
        else:
            self._tables.move_to_end(key)
        return table

    def _build(self, omega: float, noise_smooth: float) -> Table:
        g = self.grid
        w = whitener(self.model.cov(omega, noise_smooth))  # w w^T = R^-1
        partial, basis = self.model.grid_factors(self.nodes, g.kS, g.phiS, g.dphi, omega, noise_smooth, right=w)
        columnar, step = quantise_product(partial.reshape(partial.shape[:2] + (-1,)), basis, self._cells)
        columnar.flags.writeable = False
        self.builds += 1
        return Table(columnar, step, w, omega, noise_smooth)


_REGISTRY: dict = {}


def grid_tables(model, grid: SoilGrid, nodes=SLIP_NODES) -> GridTables:
    """The :class:`GridTables` of a model (the object itself), a grid and slip nodes, shared by every caller."""
    nodes = np.asarray(nodes, dtype=float)
    key = (id(model), grid.key(), nodes.tobytes())
    hit = _REGISTRY.get(key)
    if hit is not None and hit.model is model:
        return hit
    if len(_REGISTRY) >= 8:
        _REGISTRY.clear()
    tables = _REGISTRY[key] = GridTables(model, grid, nodes)
    return tables


__all__ = ["SLIP_NODES", "slip_prior", "SoilGrid", "Table", "QUANTISE_LIMIT", "quantise", "quantise_product",
           "GridTables", "grid_tables"]
