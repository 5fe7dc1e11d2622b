"""The tube of a contraction certificate: its geometry per unit P-norm radius, computed once here.

With metric ``P (n, n)``, gain ``K (m, n)`` and rate ``lambda``, the tube of radius ``r`` about a
reference ``x_ref(t)`` is ``E(t) = {x : ||x - x_ref(t)||_P <= r e^{-lambda t}}``. Over the ball
``||e||_P <= r`` (the support function of an ellipsoid, ``max c^T e = r ||P^-1/2 c||``):

    |e_i|      <= r sqrt((P^-1)_ii)                  state extent, per state
    |K_j e|    <= r ||K_j P^-1/2|| = r sqrt(K_j P^-1 K_j^T)   input margin, per input
    C e        in {p : p^T Sigma^-1 p <= r^2},  Sigma = C P^-1 C^T   position projection (2, 2)

``C`` selects the two position states. The projection is the disk of radius ``r`` in the
coordinates ``W p`` with ``W = Sigma^-1/2``, and lies in the disk of radius
``r sqrt(lambda_max(Sigma))`` about the reference position: the radius whose projection fits
a clearance ``d`` is ``r_d = d / sqrt(lambda_max(Sigma))``.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import FloatArray


def projection_shape(P: FloatArray, index: Sequence[int]) -> FloatArray:
    """``C P^-1 C^T`` (k, k): the projection of ``||e||_P <= 1`` on the states ``index`` (k,)."""
    c = list(index)
    return np.linalg.inv(P).astype(np.float64, copy=False)[np.ix_(c, c)]


def slice_shape(P: FloatArray, index: Sequence[int]) -> FloatArray:
    """``(S^T P S)^-1`` (k, k): the slice of ``||e||_P <= 1`` along the states ``index`` (k,)."""
    c = list(index)
    return np.linalg.inv(P[np.ix_(c, c)]).astype(np.float64, copy=False)


@dataclass(frozen=True, kw_only=True, eq=False)
class Tube:
    """A certified tube's data; every derived quantity is per unit P-norm radius.

    Attributes:
      K: (m, n) feedback gain of ``u = u_ref + K (x - x_ref)``.
      P: (n, n) contraction metric (symmetric positive definite).
      rate: lambda (1/s): ``||e(t)||_P <= e^{-lambda t} ||e(0)||_P`` inside ``region``.
      region: name -> (lower, upper) box of states and inputs where the certificate holds.
      state_names: (n,) and input_names: (m,) names; position_index: the two position states.
    """

    K: FloatArray = field(repr=False)
    P: FloatArray = field(repr=False)
    rate: float
    region: Mapping[str, tuple[float, float]]
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    position_index: tuple[int, int]

    @functools.cached_property
    def P_inv(self) -> FloatArray:
        """(n, n) ``P^-1``."""
        return np.linalg.inv(self.P).astype(np.float64, copy=False)

    @functools.cached_property
    def input_margin_per_radius(self) -> FloatArray:
        """(m,) ``||K_j P^-1/2||``: the largest ``|K_j e|`` over the unit ball."""
        return np.sqrt(np.einsum("ji,ik,jk->j", self.K, self.P_inv, self.K))

    @functools.cached_property
    def state_extent_per_radius(self) -> FloatArray:
        """(n,) ``sqrt((P^-1)_ii)``: the largest ``|e_i|`` over the unit ball."""
        return np.sqrt(np.diag(self.P_inv))

    @functools.cached_property
    def position_shape(self) -> FloatArray:
        """(2, 2) ``Sigma = C P^-1 C^T``: the position projection of the unit ball."""
        c = list(self.position_index)
        return self.P_inv[np.ix_(c, c)]

    @functools.cached_property
    def position_whitening(self) -> FloatArray:
        """(2, 2) ``W = Sigma^-1/2``: in the coordinates ``W p`` the projection is a disk."""
        values, vectors = np.linalg.eigh(self.position_shape)
        return vectors @ np.diag(values**-0.5) @ vectors.T

    @functools.cached_property
    def position_scale(self) -> float:
        """``sqrt(lambda_max(Sigma))``: the radius of the disk holding the unit ball's
        projection."""
        return float(np.sqrt(np.linalg.eigvalsh(self.position_shape)[-1]))

    def required_radius(self, clearance: float) -> float:
        """``r_d = d / sqrt(lambda_max(C P^-1 C^T))``: the largest radius whose position
        projection fits in a disk of radius ``d = clearance``."""
        return float(clearance / self.position_scale)

    def position_extent(self, radius: float) -> float:
        """Radius of the smallest disk holding the position projection of the ``radius`` ball."""
        return float(radius * self.position_scale)

    def input_margin(self, radius: float) -> FloatArray:
        """(m,) the largest ``|K_j e|`` over ``||e||_P <= radius``."""
        return radius * self.input_margin_per_radius

    def state_extent(self, radius: float) -> FloatArray:
        """(n,) the largest ``|e_i|`` over ``||e||_P <= radius``."""
        return radius * self.state_extent_per_radius

    def region_extent(self, radius: float) -> dict[str, float]:
        """Name -> how far the tube of radius ``radius`` reaches along each operating-region
        state or input (shrink the region by this to keep the tube inside)."""
        extent = dict(zip(self.state_names, self.state_extent(radius), strict=True))
        extent |= dict(zip(self.input_names, self.input_margin(radius), strict=True))
        return {name: float(extent[name]) for name in self.region}

    def slice_semi_axes(self, radius: float, index: Sequence[int]) -> FloatArray:
        """Semi-axes (k,), largest first, of the ball's slice along the states ``index`` (k,)
        (e.g. Init's free directions): ``{s : ||S s||_P <= radius}``."""
        c = list(index)
        return radius / np.sqrt(np.linalg.eigvalsh(self.P[np.ix_(c, c)]))
