"""A mixture of discretised truncated logistic distributions over a discrete space: the
distribution that ``reinforce/default``'s LSTM controller outputs (PixelCNN++'s mixture of
discretised logistics, Salimans et al., ICLR 2017, truncated to each parameter's range).

Each parameter ``p`` with ``n_p`` values is seen through its values' ranks ``r_v = v / (n_p - 1)``
in [0, 1]; value ``v`` owns the bin ``[r_v - h_p, r_v + h_p]``, ``h_p = 0.5 / (n_p - 1)``, so the
bins tile ``[-h_p, 1 + h_p]``. A component ``k`` puts on value ``v`` the mass of a logistic
distribution of location ``mu_kp`` and scale ``sigma_kp`` (CDF ``S(x) = 1 / (1 + exp(-x))`` of
the standardised value) over its bin, renormalised over the tiled interval:

    m_kp(v) = (S(b) - S(a)) / (S(B) - S(A)),
    a, b = (r_v -+ h_p - mu_kp) / sigma_kp,
    A, B = (-h_p - mu_kp) / sigma_kp, (1 + h_p - mu_kp) / sigma_kp.

A scenario's probability is a mixture over ``K`` components, each a product over parameters,
with a uniform floor of weight ``eps`` that keeps every scenario reachable:
    pi(a) = (1 - eps) sum_k w_k prod_p m_kp(a_p) + eps prod_p 1 / n_p.

Its cost per scenario is ``O(K P)`` exponentials whatever the number of values (a softmax head
over the values costs ``O(n_p)``): a parameter with 4,000 values costs what one with 10 does.
Sampling is exact: the component by inverse CDF, then each parameter's value by the truncated
logistic's inverse CDF (the logit), binned. One-value parameters have mass 1 on their value.

Why logistic and not Gaussian: the logistic CDF is one exponential and its inverse a logarithm,
where the Gaussian's needs ``erf``/``erfc`` and ``ndtri``. At batch 4096 on 2 CPU cores an
update (sampling, log-probabilities, eight Adam steps) took 8.7 ms with discretised Gaussians
and 2.8 ms with discretised logistics; the logistic's heavier tails also leave a little more
mass away from each component.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.search.base import categorical_from_uniform

__all__ = ["half_steps", "log_mass", "log_normaliser", "prepare", "log_prob", "sample",
           "probs_table", "sample_boundary", "boundary_probs"]


def half_steps(shape: tuple[int, ...]) -> np.ndarray:
    """``(P,)`` half a value step in rank units, ``0.5 / (n_p - 1)`` (0.5 for one value)."""
    return 0.5 / np.maximum(np.asarray(shape, np.float64) - 1.0, 1.0)


def log1mexp(x: jax.Array) -> jax.Array:
    """``log(1 - exp(x))`` for ``x <= 0``, accurate near 0 and for large ``-x``."""
    x = jnp.minimum(x, -1e-30)
    return jnp.where(x > -0.6931472, jnp.log(-jnp.expm1(x)), jnp.log1p(-jnp.exp(x)))


TINY = 1e-37  # smallest mass kept (log -85): the uniform floor dominates below it


def log_mass(lo: jax.Array, hi: jax.Array) -> jax.Array:
    """``log(S(hi) - S(lo))`` for ``lo < hi`` (``S`` the standard logistic CDF, the sigmoid),
    computed in the lower tail (``S(hi) - S(lo) = S(-lo) - S(-hi)`` when ``lo > 0``), where
    ``S(x) ~ exp(x)`` keeps a small relative error, so a bin far from the location keeps its
    small mass instead of rounding to 0 (down to ``TINY``)."""
    flip = lo > 0
    a = jnp.where(flip, -hi, lo)
    b = jnp.where(flip, -lo, hi)
    return jnp.log(jnp.maximum(jax.nn.sigmoid(b) - jax.nn.sigmoid(a), TINY))


def log_normaliser(mu: jax.Array, log_sigma: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """``(K, P)`` log of each component's mass over the tiled interval ``[-h_p, 1 + h_p]``:
    ``log S(B) + log S(-A) + log(1 - exp(A - B))`` (the identity
    ``S(B) - S(A) = S(B) S(-A) (1 - exp(A - B))``, exact in both tails)."""
    h = jnp.asarray(half_steps(shape), jnp.float32)
    inv = jnp.exp(-log_sigma)
    lo, hi = (-h - mu) * inv, (1.0 + h - mu) * inv
    return jax.nn.log_sigmoid(hi) + jax.nn.log_sigmoid(-lo) + log1mexp(lo - hi)


def prepare(mu: jax.Array, log_sigma: jax.Array, shape: tuple[int, ...]) -> tuple:
    """What every scenario's log-probability shares, per component and parameter with more
    than one value (``(K, P')`` each; one-value parameters have mass 1 and drop out):
    ``(mu, 1 / sigma, w / 2, 1 + e^w, log(e^w - 1) - log_z)``, ``w = 2 h_p / sigma`` a bin's
    width in the component's standard units (at most 10: ``sigma >= 0.1`` value steps)."""
    live = np.flatnonzero(np.asarray(shape) > 1)
    mu, log_sigma = mu[:, live], log_sigma[:, live]
    sub = tuple(np.asarray(shape)[live])
    inv = jnp.exp(-log_sigma)
    half = jnp.asarray(half_steps(sub), jnp.float32) * inv
    width = 2.0 * half
    return (mu, inv, half, 1.0 + jnp.exp(width),
            jnp.log(jnp.expm1(width)) - log_normaliser(mu, log_sigma, sub))


def log_probs_by_component(mu: jax.Array, log_sigma: jax.Array, actions: jax.Array,
                           shape: tuple[int, ...]) -> jax.Array:
    """``(K, B)`` ``sum_p log m_kp(a_p)``: each component's log-probability of each scenario
    ``actions (B, P)`` int; ``mu, log_sigma (K, P)`` in rank units.

    A bin's mass in closed form with one exponential and one logarithm: with ``c`` the bin
    centre in the component's standard units, ``t = -|c| - w / 2`` (the bin's lower end,
    mirrored to the left of the location: the logistic is symmetric) and ``E = e^w``,
    ``S(t + w) - S(t) = e^t (E - 1) / (1 + e^t (1 + E) + e^{2t} E)``; ``e^t <= 1`` and
    ``e^{2t} E <= 1``, so nothing overflows, and far out in a tail the log-mass tends to
    ``t + log(E - 1)`` without rounding to 0."""
    prepared = prepare(mu, log_sigma, shape)
    _, t, _, d = _bins(prepared, _ranks(actions, shape))
    return jnp.sum(t + prepared[4][..., None] - jnp.log(d), axis=1)


def _bins(prepared: tuple, r: jax.Array) -> tuple:
    """``(u, t, e, D)``, each ``(K, P', B)``, of :func:`prepare`'s output and the ranks ``r
    (P', B)``: ``u = r - mu``, ``t = -|u| / sigma - w / 2``, ``e = e^t``,
    ``D = 1 + e (A + e (A - 1))`` with ``A = 1 + e^w`` (a bin's log-mass is
    ``t + log(e^w - 1) - log D``). ``log D`` rather than ``log1p(D - 1)`` (3x slower on XLA
    CPU): ``D >= 1``, so the absolute error stays below 1.2e-7, a relative error of the
    probability."""
    mu, inv, half, one_e, _ = prepared
    u = r - mu[..., None]
    t = -jnp.abs(u) * inv[..., None] - half[..., None]
    e = jnp.exp(t)
    a = one_e[..., None]
    return u, t, e, 1.0 + e * (a + e * (a - 1.0))


def _ranks(actions: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """``(P', B)`` the ranks of ``actions (B, P)``'s values of parameters with more than one
    value."""
    n = np.asarray(shape)
    live = np.flatnonzero(n > 1)
    return actions[:, live].T.astype(jnp.float32) / jnp.asarray(n[live, None] - 1, jnp.float32)


@jax.custom_vjp
def _mixture(log_w, mu, inv, const, r, h):
    """``(B,)`` ``logsumexp_k (log_w_k + sum_p log m_kp)``: :func:`log_probs_by_component`'s
    mixture from ``mu, inv (K, P')``, the constant terms ``const (K, P')`` (the bin width's
    ``log(e^w - 1)`` less the normaliser), the ranks ``r (P', B)`` and the half steps ``h
    (P',)`` in rank units, with its gradient written out (below)."""
    return _mixture_fwd(log_w, mu, inv, const, r, h)[0]


def _mixture_fwd(log_w, mu, inv, const, r, h):
    half = h * inv
    u, t, e, d = _bins((mu, inv, half, 1.0 + jnp.exp(2.0 * half), const), r)  # (K, P', B)
    # sum_p (t_p - log d_p), the logarithms taken of products of up to 16 factors (each
    # < 150: no overflow); written out over the parameters, one elementwise pass over (K, B)
    comp = log_w[:, None] + jnp.sum(const, axis=1)[:, None]
    for i in range(0, d.shape[1], 16):
        prod = d[:, i]
        for j in range(i, min(i + 16, d.shape[1])):
            comp = comp + t[:, j]
            prod = prod if j == i else prod * d[:, j]
        comp = comp - jnp.log(prod)
    out = jax.nn.logsumexp(comp, axis=0)
    return out, (inv, half, h, r, u, e, d, comp, out)


def _mixture_bwd(res, g):
    """The gradient in two passes over ``(K, P', B)``: each component's share of each
    scenario, then the partials with respect to ``mu`` and ``inv`` summed over the scenarios
    at once. With ``lm = t + const - log D``, ``t = -|u| inv - h inv``,
    ``D = 1 + e (A + e (A - 1))``, ``e = e^t``, ``A = 1 + e^{2 h inv}``:
    ``dlm/dt = 1 - e (A + 2 e (A - 1)) / D``, ``dlm/dA = -e (1 + e) / D``, and ``inv`` reaches
    ``lm`` through ``t`` and ``A`` (``dA/dinv = 2 h (A - 1)``), so its partial is one sum.
    (XLA's derivative of the same expression ran ~100 kernels per gradient on a CPU.)"""
    inv, half, h, r, u, e, d, comp, out = res
    share = g[None, :] * jnp.exp(comp - out[None, :])  # (K, B): dL/dcomp
    a = (1.0 + jnp.exp(2.0 * half))[..., None]
    s = share[:, None, :]
    se = s * e / d
    dt = s - se * (a + 2.0 * e * (a - 1.0))  # share x dlm/dt
    hh = h[:, None]
    parts = jnp.stack([dt * jnp.sign(u),
                       -dt * (jnp.abs(u) + hh) - se * (1.0 + e) * (2.0 * hh) * (a - 1.0)])
    d_mu, d_inv = jnp.sum(parts, axis=-1)
    d_const = jnp.broadcast_to(jnp.sum(share, axis=1)[:, None], inv.shape)
    return (jnp.sum(share, axis=1), d_mu * inv, d_inv, d_const, jnp.zeros_like(r),
            jnp.zeros_like(h))


_mixture.defvjp(_mixture_fwd, _mixture_bwd)


def log_prob(mix_logits: jax.Array, mu: jax.Array, log_sigma: jax.Array, actions: jax.Array,
             shape: tuple[int, ...], eps) -> jax.Array:
    """``(B,)`` ``log pi(a)`` of each scenario ``actions (B, P)`` under the mixture
    (``mix_logits (K,)``, ``mu, log_sigma (K, P)``) with a uniform floor of weight ``eps`` in
    (0, 1). The
    same value as :func:`log_probs_by_component`'s mixture, with a gradient written out for
    speed (checked against automatic differentiation of that function). Every ``sigma`` at
    least ``0.1`` value steps, as the controller keeps them (``batched.SIGMA_MIN_STEPS``): a
    bin is then at most 10 standard units wide, which the closed form's float32 range needs."""
    log_w = jax.nn.log_softmax(mix_logits)
    if np.all(np.asarray(shape) == 1):
        mixture = jnp.zeros(actions.shape[:1], jnp.float32)
    else:
        live = np.flatnonzero(np.asarray(shape) > 1)
        mu_l, inv, _, _, const = prepare(mu, log_sigma, shape)
        h = jnp.asarray(half_steps(tuple(np.asarray(shape)[live])), jnp.float32)
        mixture = _mixture(log_w, mu_l, inv, const, _ranks(actions, shape), h)
    log_uniform = -float(np.sum(np.log(np.asarray(shape, np.float64))))
    return jnp.logaddexp(jnp.log1p(-eps) + mixture, jnp.log(eps) + log_uniform)


def sample(mix_logits: jax.Array, mu: jax.Array, log_sigma: jax.Array, u: jax.Array,
           shape: tuple[int, ...], eps) -> jax.Array:
    """``(B, P)`` int32 scenarios from uniforms ``u (B, P + 2)`` in [0, 1): ``u[:, 0]``
    chooses the uniform floor (``u[:, 0] < eps``) or the mixture, ``u[:, 1]`` the component,
    ``u[:, 2:]`` each parameter's value (uniformly under the floor, else by the component's
    inverse CDF).

    Laid out parameters x scenarios, the chosen components' means and widths picked by a
    product with the one-hot choice (exact for finite means and widths: one term of the sum
    is non-zero) rather than a gather: on XLA CPU the gather kept the elementwise work that
    follows from vectorising, and a minor axis of ``P`` values vectorises poorly (four
    learners' draws at batch 4096 on 2 cores, uniforms included: 0.38-0.52 ms instead of
    1.0-1.5 ms for draws gathered scenario by scenario; the same draws on spaces of up to 200
    values per parameter, while with 250-4000 values 1 to 23 in a million drawn values move by
    one value, the vectorised and the scalar logarithm rounding differently at a bin's edge)."""
    n = np.asarray(shape)
    span = jnp.asarray(np.maximum(n - 1, 1), jnp.float32)[:, None]
    h = jnp.asarray(half_steps(shape), jnp.float32)[:, None]
    k = categorical_from_uniform(u[:, 1], jax.nn.softmax(mix_logits))  # (B,)
    one_hot = (k[None, :] == jnp.arange(mix_logits.shape[0])[:, None]).astype(jnp.float32)
    pick = lambda x: jnp.dot(x.T, one_hot, precision=jax.lax.Precision.HIGHEST)  # noqa: E731
    m, s = pick(mu), pick(jnp.exp(log_sigma))  # (P, B)
    ut = u[:, 2:].T
    lo, hi = jax.nn.sigmoid((-h - m) / s), jax.nn.sigmoid((1.0 + h - m) / s)
    q = jnp.clip(lo + ut * (hi - lo), 1e-7, 1.0 - 1e-7)
    x = m + s * (jnp.log(q) - jnp.log1p(-q))  # the logit; in [-h, 1 + h] up to rounding
    top = jnp.asarray(n - 1, jnp.float32)[:, None]
    v = jnp.clip(jnp.round(x * span), 0, top)
    flat = jnp.minimum(jnp.floor(ut * jnp.asarray(n, jnp.float32)[:, None]), top)
    return jnp.where(u[None, :, 0] < eps, flat, v).astype(jnp.int32).T


def probs_table(mix_logits, mu, log_sigma, shape: tuple[int, ...], eps) -> jax.Array:
    """``(P, max_n)`` each parameter's marginal probabilities (padded with zeros): for figures
    and tests, ``O(K P max_n)``."""
    n = np.asarray(shape)
    width = int(n.max())
    v = jnp.arange(width)
    w = jax.nn.softmax(mix_logits)

    def marginal(p):
        acts = jnp.zeros((width, len(shape)), jnp.int32).at[:, p].set(v)
        per_k = jax.vmap(lambda a: _component_mass(mu, log_sigma, a, shape, p))(acts)  # (n, K)
        mix = (1 - eps) * per_k @ w + eps / n[p]
        return jnp.where(v < n[p], mix, 0.0)

    return jnp.stack([marginal(p) for p in range(len(shape))])


def _component_mass(mu, log_sigma, action, shape, p):
    n = np.asarray(shape)
    h = jnp.asarray(half_steps(shape), jnp.float32)[p]
    r = action[p].astype(jnp.float32) / float(max(n[p] - 1, 1))
    s = jnp.exp(log_sigma[:, p])
    lm = log_mass((r - h - mu[:, p]) / s, (r + h - mu[:, p]) / s) - \
        log_mass((-h - mu[:, p]) / s, (1.0 + h - mu[:, p]) / s)
    return jnp.exp(lm) if n[p] > 1 else jnp.ones_like(lm)


def sample_boundary(u: jax.Array, shape: tuple[int, ...], width) -> jax.Array:
    """``(B, P)`` int32 scenarios from uniforms ``u (B, P)`` (two-dimensional) in [0, 1) under the
    boundary distribution: each parameter independently uniform over its values (``u < 1/3``),
    near its lowest value (``1/3 <= u < 2/3``) or near its highest (``u >= 2/3``); "near" an
    exponential of mean ``width`` (rank units) away from the end, rounded to the nearest value
    and capped at the other end. Boundary-value testing for every parameter at once: each draw
    puts some parameters at an end of their range and the others anywhere. An end value gets
    about ``(1 - exp(-1 / (2 width (n - 1)))) / 3`` (up to ``1 / (6 width)`` times its uniform
    mass, 8x at width 0.02), a value inside the range a third of its uniform mass, so a failure
    region on a face or an edge of the box (some parameters at an end, the rest free) gets
    several times its uniform mass per end parameter (:func:`boundary_probs` gives each value's
    probability)."""
    n = jnp.asarray(shape, jnp.float32)[:, None]
    span = jnp.maximum(n - 1.0, 1.0)
    x = 3.0 * u.T  # [0, 3): which third, and where in it; parameters x scenarios (a minor
    # axis of P values vectorises poorly on XLA CPU)
    flat = jnp.minimum(jnp.floor(x * n), n - 1.0)
    frac = x - jnp.floor(x)
    steps = jnp.minimum(jnp.round(-width * jnp.log1p(-frac) * span), n - 1.0)
    v = jnp.where(x < 1.0, flat, jnp.where(x < 2.0, steps, n - 1.0 - steps))
    return v.astype(jnp.int32).T


def boundary_probs(n: int, width: float) -> np.ndarray:
    """``(n,)`` float64 probabilities of :func:`sample_boundary` over one parameter's ``n``
    values (for tests and estimates)."""
    if n == 1:
        return np.ones(1)
    span = n - 1.0
    edges = np.exp(-(np.arange(n) + 0.5) / (width * span))  # P(steps > v)
    low = np.concatenate([[1.0], edges[:-1]]) - np.concatenate([edges[:-1], [0.0]])
    return (1.0 / n + low + low[::-1]) / 3.0
