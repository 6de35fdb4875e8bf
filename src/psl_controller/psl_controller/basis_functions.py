"""Normalised Gaussian basis functions on the DMP phase (eq. 2.24).

``psi_k(x) = exp(-V_k (x - C_k)^2)``, normalised by ``sum_k psi_k(x)``. Centres ``C_k`` are
equally spaced on the phase interval [0, 1]; the widths follow from the centre spacing ``h``:
``sigma = width_factor * h`` and ``V_k = 1 / (2 sigma^2)`` (fixed centres and variances as in
Reinhart and Steil 2015). Pure numpy; no ROS.
"""

import numpy as np


class NormalizedGaussianBasis:
    """K normalised Gaussians on the phase interval [0, 1] (eq. 2.24).

    Args:
        n_basis: number of Gaussians K (>= 1). With K = 1 the single centre is 0.5 and the
            normalised activation is identically 1.
        width_factor: standard deviation of each Gaussian in units of the centre spacing (> 0).

    Raises:
        ValueError: ``n_basis < 1`` or a non-positive / non-finite ``width_factor``.
    """

    def __init__(self, n_basis: int, width_factor: float = 0.5) -> None:
        if isinstance(n_basis, bool) or int(n_basis) != n_basis or n_basis < 1:
            raise ValueError(f'n_basis must be an integer >= 1, got {n_basis!r}')
        if not (np.isfinite(width_factor) and width_factor > 0.0):
            raise ValueError(f'width_factor must be finite and > 0, got {width_factor!r}')
        self._n_basis = int(n_basis)
        if self._n_basis == 1:
            spacing = 1.0
            self._centers = np.array([0.5])  # (K,)
        else:
            spacing = 1.0 / (self._n_basis - 1)
            self._centers = np.linspace(0.0, 1.0, self._n_basis)  # (K,)
        sigma = width_factor * spacing
        self._widths = np.full(self._n_basis, 1.0 / (2.0 * sigma**2))  # V_k: (K,)

    @property
    def n_basis(self) -> int:
        return self._n_basis

    @property
    def centers(self) -> np.ndarray:
        """Centres C_k, shape (K,)."""
        return self._centers.copy()

    @property
    def widths(self) -> np.ndarray:
        """Inverse-variance factors V_k, shape (K,)."""
        return self._widths.copy()

    def activations(self, x: np.ndarray) -> np.ndarray:
        """Normalised activations psi_k(x) / sum_j psi_j(x) (eq. 2.24).

        Computed with the largest exponent subtracted per row, so rows never underflow to 0/0.

        Args:
            x: phase values, shape (T,) (a scalar is treated as T = 1).

        Returns:
            activations, shape (T, K); every row sums to 1.
        """
        x = np.atleast_1d(np.asarray(x, dtype=float)).reshape(-1)  # (T,)
        exponents = -self._widths * (x[:, None] - self._centers) ** 2  # (T, K)
        exponents -= exponents.max(axis=1, keepdims=True)
        psi = np.exp(exponents)  # (T, K)
        return psi / psi.sum(axis=1, keepdims=True)
