"""CMA-ES on the unit cube, several instances stepped together (ask/tell; one batched objective call per generation).

Hansen's tutorial settings ("The CMA Evolution Strategy: A Tutorial",
arXiv:1604.00772), with box handling by clipping plus a penalty. Kept here
rather than taken from the ``cma`` package so that several instances (one
per value of a categorical parameter) share one simulation batch per
generation and draw from the caller's generator. Pure numpy.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np


class CMA:
    """One CMA-ES instance on the unit cube (ask/tell), Hansen's tutorial settings.

    Points outside the cube are clipped for evaluation and penalised by
    their squared distance to it (so the mean stays inside). Several
    instances can be stepped together so that their candidates share one
    simulation batch.
    """

    def __init__(self, u0, sigma0: float, lam: int, rng: np.random.Generator):
        n = len(u0)
        self.n, self.lam, self.rng = n, lam, rng
        self.mu = lam // 2
        w = np.log(self.mu + 0.5) - np.log(np.arange(1, self.mu + 1))
        self.w = w / w.sum()
        self.mueff = 1.0 / np.sum(self.w**2)
        mueff = self.mueff
        self.cc = (4 + mueff / n) / (n + 4 + 2 * mueff / n)
        self.cs = (mueff + 2) / (n + mueff + 5)
        self.c1 = 2 / ((n + 1.3) ** 2 + mueff)
        self.cmu = min(1 - self.c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
        self.damps = 1 + 2 * max(0.0, math.sqrt((mueff - 1) / (n + 1)) - 1) + self.cs
        self.chin = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))
        self.m = np.clip(np.array(u0, dtype=float), 0.0, 1.0)
        self.sigma = float(sigma0)
        self.pc = np.zeros(n)
        self.ps = np.zeros(n)
        self.C = np.eye(n)
        self.B = np.eye(n)
        self.D = np.ones(n)
        self.gen = 0
        self.best_u = self.m.copy()
        self.best_f = np.inf
        self._X = None

    def ask(self) -> np.ndarray:
        """``lam`` candidates, clipped to the cube."""
        z = self.rng.standard_normal((self.lam, self.n))
        self._X = self.m + self.sigma * (z @ (self.B * self.D).T)
        return np.clip(self._X, 0.0, 1.0)

    def tell(self, fx: np.ndarray) -> None:
        X = self._X
        Xc = np.clip(X, 0.0, 1.0)
        fx = np.asarray(fx, dtype=float)
        finite = fx[np.isfinite(fx)]
        scale = np.max(np.abs(finite), initial=1.0)
        fx = np.where(np.isfinite(fx), fx, 10 * scale) + 1e3 * scale * np.sum((X - Xc) ** 2, axis=1)
        order = np.argsort(fx)
        if fx[order[0]] < self.best_f:
            self.best_f, self.best_u = float(fx[order[0]]), Xc[order[0]].copy()
        self.gen += 1
        n, cs, cc, c1, cmu = self.n, self.cs, self.cc, self.c1, self.cmu
        sel = order[: self.mu]
        m_old = self.m
        self.m = self.w @ X[sel]
        y_w = (self.m - m_old) / self.sigma
        inv_sqrt = (self.B / self.D) @ self.B.T
        self.ps = (1 - cs) * self.ps + math.sqrt(cs * (2 - cs) * self.mueff) * (inv_sqrt @ y_w)
        hsig = np.linalg.norm(self.ps) / math.sqrt(1 - (1 - cs) ** (2 * self.gen)) / self.chin < 1.4 + 2 / (n + 1)
        self.pc = (1 - cc) * self.pc + hsig * math.sqrt(cc * (2 - cc) * self.mueff) * y_w
        Y = (X[sel] - m_old) / self.sigma
        C = (1 - c1 - cmu) * self.C + c1 * (np.outer(self.pc, self.pc) + (1 - hsig) * cc * (2 - cc) * self.C)
        C += cmu * (Y.T * self.w) @ Y
        self.sigma *= math.exp((cs / self.damps) * (np.linalg.norm(self.ps) / self.chin - 1))
        self.sigma = min(self.sigma, 1.0)
        self.C = np.triu(C) + np.triu(C, 1).T
        evals, self.B = np.linalg.eigh(self.C)
        self.D = np.sqrt(np.maximum(evals, 1e-20))

    @property
    def spread(self) -> float:
        return self.sigma * float(self.D.max())




def run_cmas(f: Callable[[np.ndarray], np.ndarray], starts, rng: np.random.Generator, lam: int, max_gen: int,
             dims=None, keep_after: dict | None = None, tol: float = 1e-4,
             progress: Callable[[], None] | None = None) -> list[tuple[np.ndarray, float]]:
    """Step several CMA-ES instances together (one batched call of ``f`` per generation).

    ``f`` maps ``(P, D)`` points of the unit cube to ``(P,)`` values.
    ``starts``: ``(u0, sigma0)`` pairs of full points; each instance searches
    the coordinates ``dims`` (default all) and keeps the others at its
    start's values (e.g. a categorical parameter). ``keep_after``:
    ``{generation: k}`` keeps the ``k`` instances with the best values so far
    (successive halving). Returns ``(best point, best value)`` per surviving
    instance, best first.
    """
    starts = list(starts)
    D = len(starts[0][0])
    dims = np.arange(D) if dims is None else np.asarray(dims, dtype=np.int64)
    runs = [(CMA(np.asarray(u)[dims], s, lam, rng), np.array(u, dtype=float)) for u, s in starts]
    keep_after = keep_after or {}
    for gen in range(1, max_gen + 1):
        active = [(r, t) for r, t in runs if r.spread >= tol]
        if not active:
            break
        blocks = []
        for r, t in active:
            U = np.tile(t, (lam, 1))
            U[:, dims] = r.ask()
            blocks.append(U)
        fx = f(np.vstack(blocks))
        for j, (r, _) in enumerate(active):
            r.tell(fx[j * lam : (j + 1) * lam])
        if gen in keep_after:
            runs = sorted(runs, key=lambda rt: rt[0].best_f)[: keep_after[gen]]
        if progress is not None:
            progress()
    out = []
    for r, t in sorted(runs, key=lambda rt: rt[0].best_f):
        u = t.copy()
        u[dims] = r.best_u
        out.append((u, r.best_f))
    return out
