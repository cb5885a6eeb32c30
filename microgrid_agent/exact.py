"""Sums of products that give the same bits on every machine.

numpy's ``@`` and ``einsum`` hand their sums to BLAS, which picks its kernels for the CPU it runs on (OpenBLAS's
``DYNAMIC_ARCH``) and adds the terms in an order of the kernel's own: AVX-512, AVX2 and SSE kernels give sums that
differ in their last bits. A decomposition's path turns on such bits (a cut's right-hand side, an upper bound: which
x^ a MILP master returns next), and an agent's bid carries them to the DMO, so the same seed gave another schedule and
other statements on another machine (docs/solver.md, "One machine, two paths"). Here each product is rounded once
(the same everywhere) and each sum is exact before its one rounding (``math.fsum``), whatever the order.
"""

from __future__ import annotations

import math

import numpy as np


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum_i a_i b_i of two vectors, correctly rounded."""
    return math.fsum(np.multiply(a, b).ravel())


def matvec(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(rows,) a @ x, each row's sum correctly rounded."""
    products = np.multiply(a, x)
    return np.array([math.fsum(row) for row in products.reshape(len(products), -1)])


def weighted(weight: np.ndarray, data: np.ndarray, axis: int) -> np.ndarray:
    """``data`` with its ``axis`` (length S) replaced by the (G, S) ``weight``'s rows: out[..., g, ...] = sum_s
    weight[g, s] data[..., s, ...], each sum correctly rounded."""
    moved = np.moveaxis(np.asarray(data, float), axis, -1)  # (..., S)
    products = moved[..., None, :] * weight  # (..., G, S)
    sums = np.array([math.fsum(row) for row in products.reshape(-1, products.shape[-1])])
    return np.moveaxis(sums.reshape(products.shape[:-1]), -1, axis)
