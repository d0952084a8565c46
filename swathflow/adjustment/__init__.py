"""Weighted least-squares adjustment with priors (generic: no sensor knowledge).

A :class:`Problem` holds named unknowns and observation groups; :func:`solve` estimates
the unknowns by Gauss-Newton with Levenberg-Marquardt damping, and returns a
:class:`Solution` with covariance, correlation, variance components and the points a
robust phase or data snooping rejected.

Conventions
-----------
- A nonlinear group is a function ``fn(x, jacobian) -> (r, J)``: ``r`` (m,) are the
  residuals *observed minus computed* at the unknowns ``x`` (NaN where an observation
  cannot be computed; it is then left out of that iteration), ``J`` (m, n) the partial
  derivatives of the *computed* values with respect to all unknowns (dense or
  ``scipy.sparse``; ``None`` when ``jacobian`` is False).
- Every observation has an a-priori sigma and a variance-component label; components
  can be estimated from the data (variance component estimation, Foerstner's iterative
  method with redundancy numbers).
- Observations belong to *points* (e.g. the line and element of one image point): the
  robust phase and data snooping test and reject whole points with their 2-D (k-D)
  statistic ``v' Qvv^-1 v``, chi-square with k degrees of freedom.
- Priors are pseudo-observations ``x_i = value_i +- sigma_i``; linear (soft) constraints
  are observations ``A x = b +- sigma``; hard equality constraints ``C x = d`` are solved
  exactly (bordered normal equations).
- Fixed unknowns keep their start values and have zero covariance.

Dense normal equations are used when the Jacobian is dense; sparse ones (SuperLU) when any
group returns a sparse Jacobian or ``sparse=True``. Redundancy numbers (needed by variance
component estimation and snooping) need the covariance of all free unknowns, formed densely
up to ``max_dense_cov`` free unknowns.
"""
from swathflow.adjustment.problem import (AdjustmentError, Group, Problem,
                                          RankDeficiencyError, Solution)
from swathflow.adjustment.solver import solve

__all__ = ["AdjustmentError", "Group", "Problem", "RankDeficiencyError", "Solution", "solve"]
