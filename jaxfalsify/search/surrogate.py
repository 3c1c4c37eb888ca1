"""A small Gaussian-process surrogate of the learning signal, for screening candidates.

``reinforce/default`` draws several candidates per scenario it asks; until it has a collision,
a GP fitted to its last evaluations (``surrogate`` of them) ranks the new candidates by the
upper confidence bound ``mean + kappa * std`` and the best are asked (README: "Surrogate
screening"). Everything here is fixed-shape and jit-friendly: empty history slots are masked,
not dropped.

Model: zero-mean GP on the standardised signal, squared-exponential kernel with one length
scale on the value ranks scaled to ``[0, 1]`` per parameter, a nugget of ``NOISE``; the length
scale is the one of ``LENGTH_SCALES`` with the highest log marginal likelihood (Rasmussen &
Williams, *Gaussian Processes for Machine Learning*, 2006, Eq. 2.25-2.26 and 2.30).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

LENGTH_SCALES = (0.03, 0.06, 0.12, 0.25, 0.5)  # candidates, fractions of every range
NOISE = 1e-3  # nugget, in units of the standardised signal's variance
MIN_POINTS = 3  # fewer valid history points: no model (every score 0)


def unit(indices: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Value ranks ``(..., P)`` int -> ``[0, 1]`` per parameter (float32; 0 for a parameter of
    one value)."""
    span = jnp.maximum(jnp.asarray(shape, jnp.float32) - 1, 1.0)
    return indices.astype(jnp.float32) / span


def posterior(x: jax.Array, y: jax.Array, z: jax.Array):
    """GP posterior at ``z (N, P)`` given points ``x (H, P)`` and signals ``y (H,)`` (both in
    unit coordinates; a non-finite ``y`` marks an empty slot). Returns ``(mean (N,), std (N,),
    length_scale ())`` in the signal's units (mean 0, std 0 when fewer than ``MIN_POINTS``
    slots are filled)."""
    ok = jnp.isfinite(y)
    n = jnp.maximum(jnp.sum(ok), 1)
    y0 = jnp.where(ok, y, 0.0)
    mu = jnp.sum(y0) / n
    sd = jnp.sqrt(jnp.sum(jnp.where(ok, (y0 - mu) ** 2, 0.0)) / n)
    sd = jnp.where(sd > 0, sd, 1.0)
    t = jnp.where(ok, (y0 - mu) / sd, 0.0)  # standardised targets, 0 in empty slots
    both = ok[:, None] & ok[None, :]
    d2 = jnp.sum((x[:, None, :] - x[None, :, :]) ** 2, -1)  # (H, H)
    dz = jnp.sum((z[:, None, :] - x[None, :, :]) ** 2, -1)  # (N, H)
    # an empty slot is an independent unit-variance point with target 0: no influence
    diag = jnp.diag(jnp.where(ok, NOISE, 1.0))

    def fit(ell):
        k = jnp.where(both, jnp.exp(-0.5 * d2 / ell**2), 0.0) + diag
        chol = jnp.linalg.cholesky(k)
        alpha = jax.scipy.linalg.cho_solve((chol, True), t)
        # log marginal likelihood up to a constant (empty slots add log 1 = 0)
        lml = -0.5 * t @ alpha - jnp.sum(jnp.log(jnp.diag(chol)))
        return lml, chol, alpha

    ells = jnp.asarray(LENGTH_SCALES, jnp.float32)
    lmls, chols, alphas = jax.vmap(fit)(ells)  # every candidate fitted once
    best = jnp.argmax(jnp.where(jnp.isfinite(lmls), lmls, -jnp.inf))
    ell, chol, alpha = ells[best], chols[best], alphas[best]
    ks = jnp.where(ok[None, :], jnp.exp(-0.5 * dz / ell**2), 0.0)  # (N, H)
    v = jax.scipy.linalg.solve_triangular(chol, ks.T, lower=True)  # (H, N)
    var = jnp.maximum(1.0 - jnp.sum(v * v, 0), 0.0)
    enough = jnp.sum(ok) >= MIN_POINTS
    mean = jnp.where(enough, mu + sd * (ks @ alpha), 0.0)
    std = jnp.where(enough, sd * jnp.sqrt(var), 0.0)
    return mean, std, ell


def ucb(x: jax.Array, y: jax.Array, z: jax.Array, kappa) -> jax.Array:
    """Upper confidence bound ``mean + kappa * std`` ``(N,)`` at ``z`` (see :func:`posterior`);
    all 0 without a model."""
    mean, std, _ = posterior(x, y, z)
    return mean + kappa * std
