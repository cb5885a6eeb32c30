"""Sums of products that give the same bits on every machine.

numpy's ``@`` and ``einsum`` hand their sums to BLAS, which picks its kernels for the CPU it runs on (OpenBLAS's
``DYNAMIC_ARCH``) and adds the terms in an order of the kernel's own: AVX-512, AVX2 and SSE kernels give sums that
differ in their last bits. A decomposition's path turns on such bits (a cut's right-hand side, an upper bound: which
x^ a MILP master returns next), and an agent's bid carries them to the DMO, so the same seed gave another schedule and
other statements on another machine (docs/solver.md, "The same path on every machine"); a feeder's flows and prices
carried them into the awards. Here each product is rounded once (the same everywhere) and each sum is exact before
its one rounding (``math.fsum``), whatever the order; a 0/1 matrix's sums, whose terms are exact, are added in numpy's
own pairwise order, which is the same on every CPU.
"""

from __future__ import annotations

import math

import numpy as np


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum_i a_i b_i of two vectors, correctly rounded."""
    return math.fsum(np.multiply(a, b).ravel())


def matvec(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(rows,) a @ x for a (rows, n) matrix, each row's sum correctly rounded. The terms of x's zeros are left out
    (they add nothing to an exact sum): a feeder's limits' duals are mostly zero."""
    x = np.asarray(x, float)
    terms = np.flatnonzero(x)
    return _sums(np.asarray(a, float)[:, terms] * x[terms])


def weighted(weight: np.ndarray, data: np.ndarray, axis: int) -> np.ndarray:
    """``data`` with its ``axis`` (length S) replaced by the (G, S) ``weight``'s rows: out[..., g, ...] = sum_s
    weight[g, s] data[..., s, ...], each sum correctly rounded."""
    moved = np.moveaxis(np.asarray(data, float), axis, -1)  # (..., S)
    return np.moveaxis(_sums(moved[..., None, :] * weight), -1, axis)  # the products (..., G, S) summed over S


def _sums(products: np.ndarray) -> np.ndarray:
    """``products`` summed over their last axis, each sum correctly rounded."""
    flat = products.reshape(math.prod(products.shape[:-1]), products.shape[-1])  # no -1: a row may have no terms
    return np.array([math.fsum(row) for row in flat], dtype=float).reshape(products.shape[:-1])


def masked_sums(mask: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(..., rows) sum_j mask[r, j] x[..., j] for a 0/1 ``mask`` (rows, n): a feeder's line flows and voltage drops
    (``Network.downstream``). One row of ``x`` at a time, so a feeder of a thousand buses needs no cube in memory."""
    flat = np.asarray(x, float).reshape(-1, mask.shape[1])
    sums = np.array([(mask * row).sum(axis=1) for row in flat], dtype=float).reshape(len(flat), mask.shape[0])
    return sums.reshape(*np.shape(x)[:-1], mask.shape[0])
