"""A convex quadratic program through HiGHS, answered as ``scipy.optimize.linprog`` answers an LP.

The AC-faithful clearing's proximal iterations (``distflow._settle``) add a convex quadratic term to an hour's LP;
scipy's ``linprog`` takes no quadratic term, so they reach HiGHS's QP solver through highspy's public model API.
The answer carries the fields of scipy's ``OptimizeResult`` that the clearing reads, with scipy's signs: ``x``,
``fun``, ``status`` (0 optimal, 2 otherwise), ``message``, and ``marginals`` of ``eqlin``, ``ineqlin`` (<= 0),
``lower`` (>= 0) and ``upper`` (<= 0): each the change of the objective per unit of its right side or bound.
"""

from __future__ import annotations

from types import SimpleNamespace

import highspy
import numpy as np
import scipy.sparse as sp

from microgrid_agent.solvers.threads import HIGHS_THREADS


def minimise(c: np.ndarray, hessian: sp.sparray, a_eq: np.ndarray, b_eq: np.ndarray, a_ub: np.ndarray,
             b_ub: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> SimpleNamespace:
    """Minimise c x + x' H x / 2 subject to A_eq x = b_eq, A_ub x <= b_ub and lower <= x <= upper, for a symmetric
    positive semidefinite ``hessian`` H (columns x columns)."""
    a = sp.csc_array(np.vstack([a_ub, a_eq]))
    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = len(c), a.shape[0]
    lp.col_cost_, lp.col_lower_, lp.col_upper_ = c, lower, upper
    lp.row_lower_ = np.concatenate([np.full(len(b_ub), -highspy.kHighsInf), b_eq])
    lp.row_upper_ = np.concatenate([b_ub, b_eq])
    lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
    lp.a_matrix_.start_, lp.a_matrix_.index_, lp.a_matrix_.value_ = a.indptr, a.indices, a.data
    triangle = sp.csc_array(sp.tril(hessian))  # HiGHS reads the lower triangle, column by column
    quadratic = highspy.HighsHessian()
    quadratic.dim_, quadratic.format_ = len(c), highspy.HessianFormat.kTriangular
    quadratic.start_, quadratic.index_, quadratic.value_ = triangle.indptr, triangle.indices, triangle.data
    highs = highspy.Highs()
    highs.setOptionValue("output_flag", False)
    highs.setOptionValue("threads", HIGHS_THREADS)  # the process's one HiGHS scheduler has this many
    highs.passModel(lp)
    highs.passHessian(quadratic)
    highs.run()
    status, solution = highs.getModelStatus(), highs.getSolution()
    row_dual, col_dual = np.array(solution.row_dual), np.array(solution.col_dual)
    return SimpleNamespace(
        x=np.array(solution.col_value), fun=highs.getInfo().objective_function_value,
        status=0 if status == highspy.HighsModelStatus.kOptimal else 2, message=highs.modelStatusToString(status),
        ineqlin=SimpleNamespace(marginals=row_dual[:len(b_ub)]), eqlin=SimpleNamespace(marginals=row_dual[len(b_ub):]),
        lower=SimpleNamespace(marginals=np.maximum(col_dual, 0.0)),
        upper=SimpleNamespace(marginals=np.minimum(col_dual, 0.0)))
