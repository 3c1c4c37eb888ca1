"""A small Gaussian-process surrogate of the learning signal, for choosing among candidates.

``reinforce/screened`` draws several candidates per scenario it asks; until it has a collision,
a GP fitted to its recent and best evaluations picks which of the new candidates are asked
(README: "Surrogate screening"), one batch at a time by GP-BUCB: the highest upper confidence
bound ``mean + kappa * std`` first, then each further pick with the variance shrunk as if the
earlier picks had been observed (Desautels, Krause & Burdick, "Parallelizing
exploration-exploitation tradeoffs in Gaussian process bandit optimization", JMLR 15, 2014),
so a batch spreads over the promising candidates instead of piling onto one. Everything here
is fixed-shape and jit-friendly: empty data slots are masked, not dropped.

Model: a GP on the standardised signal with a constant prior mean ``prior`` (in standard
deviations from the data's mean: 0 by default; ``reinforce/screened`` uses -0.5, so a region
without data is expected somewhat worse than the average evaluation, and an uncertain candidate
far from everything wins a pick only where the model sees little that is good nearby),
a stationary kernel on the value ranks scaled to ``[0, 1]`` per parameter (squared exponential
or Matern 5/2, :func:`kernel`, or ``auto``: whichever of the two the marginal likelihood prefers,
chosen with the length scales; ``reinforce/screened`` uses ``auto``), a nugget of ``NOISE``.
Length scales are chosen by the log marginal likelihood (Rasmussen & Williams, *Gaussian
Processes for Machine Learning*, 2006, Alg. 2.1, Eq. 2.30): one for all parameters among
``LENGTH_SCALES`` (:func:`posterior`), or one per parameter (automatic relevance
determination), refined one parameter at a time among
``ARD_SCALES`` (:func:`refine`; ``reinforce/screened`` refines every parameter in turn at each
of its first updates, then one per update): a parameter that does not matter (CARLA's weather
for the Traffic Manager) gets a long scale and stops spreading the candidates.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.search.controller import mm  # full float32 products (not TF32) on GPUs
from jaxfalsify.search.memory import equals_an_earlier

__all__ = [
    "LENGTH_SCALES", "ARD_SCALES", "ARD_START", "NOISE", "unit", "cholesky", "solve_lower",
    "solve_upper", "KERNELS", "check_kernel", "kernel", "fit", "best_fit", "refine", "predict",
    "posterior", "ucb", "batch_ucb", "ScreenState", "GPScreen"
]

LENGTH_SCALES = (0.03, 0.06, 0.12, 0.25, 0.5)  # candidates, fractions of every range
ARD_SCALES = (0.03, 0.06, 0.12, 0.25, 0.5, 1.0, 4.0)  # candidates per parameter
ARD_START = 0.12  # every parameter's scale before it is refined
NOISE = 1e-3  # nugget, in units of the standardised signal's variance
MIN_POINTS = 3  # fewer valid data points: no model (mean 0, prior variance)


def unit(indices: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Value ranks ``(..., P)`` int -> ``[0, 1]`` per parameter (float32; 0 for a parameter of
    one value)."""
    span = jnp.maximum(jnp.asarray(shape, jnp.float32) - 1, 1.0)
    return indices.astype(jnp.float32) / span


class Model(NamedTuple):
    """A GP fitted to ``x (H, P)`` (unit coordinates) with length scales ``ell (P,)``."""

    x: jax.Array  # (H, P)
    ok: jax.Array  # (H,) bool, filled slots
    ell: jax.Array  # (P,) length scales, fractions of each range
    chol: jax.Array  # (H, H) Cholesky factor of K + nugget (empty slots: identity rows)
    alpha: jax.Array  # (H,) (K + nugget)^-1 t, t the standardised targets less the prior
    # mean (0 in empty slots)
    prior: jax.Array  # () the prior mean, standardised
    mu: jax.Array  # () the signal's mean over the filled slots
    sd: jax.Array  # () its standard deviation (1 if 0)
    lml: jax.Array  # () log marginal likelihood, up to a constant
    enough: jax.Array  # () bool, at least MIN_POINTS filled slots
    m52: jax.Array  # () bool, the Matern 5/2 correlation (else the squared exponential)


def cholesky(a: jax.Array) -> jax.Array:
    """Lower Cholesky factor ``(n, n)`` of a symmetric positive definite ``a (n, n)`` (NaN
    where ``a`` is not positive definite), column by column in plain XLA ops.

    Not ``jnp.linalg.cholesky``: jaxlib's CPU LAPACK kernels split a batch of matrices over
    the intra-op thread pool and block a pool thread until the pieces finish, which deadlocks
    when several CPU devices run the GP at once (seen with 4 forced host devices on 2 cores,
    jax 0.10.2); at these sizes (n = 160, a batch of 7) this loop is also faster (6.2 vs
    8.9 ms on 2 CPU cores).
    """
    n = a.shape[-1]
    rows = jnp.arange(n)

    def column(j, chol):
        c = a[:, j] - mm(chol, chol[j, :])  # columns >= j of chol are still 0
        d = jnp.sqrt(c[j])
        return chol.at[:, j].set(jnp.where(rows > j, c / d, jnp.where(rows == j, d, 0.0)))

    return jax.lax.fori_loop(0, n, column, jnp.zeros_like(a))


def solve_lower(chol: jax.Array, b: jax.Array) -> jax.Array:
    """``x (n, m)`` with ``chol @ x = b``, ``chol (n, n)`` lower triangular (forward
    substitution)."""
    def row(i, x):
        return x.at[i].set((b[i] - mm(chol[i], x)) / chol[i, i])

    return jax.lax.fori_loop(0, b.shape[0], row, jnp.zeros_like(b))


def solve_upper(chol: jax.Array, b: jax.Array) -> jax.Array:
    """``x (n, m)`` with ``chol.T @ x = b``, ``chol (n, n)`` lower triangular (back
    substitution)."""
    n = b.shape[0]

    def row(k, x):
        i = n - 1 - k
        return x.at[i].set((b[i] - mm(chol[:, i], x)) / chol[i, i])

    return jax.lax.fori_loop(0, n, row, jnp.zeros_like(b))


def _sq_dist(a: jax.Array, b: jax.Array, ell: jax.Array) -> jax.Array:
    """``(N, M)`` squared distances of ``a (N, P)`` and ``b (M, P)`` in length-scale units."""
    return jnp.sum(jnp.square((a[:, None, :] - b[None, :, :]) / ell), -1)


KERNELS = ("se", "matern52", "auto")


def check_kernel(kind: str) -> None:
    """One line naming the kernels known, for a ``kind`` not among them."""
    if kind not in KERNELS:
        raise ValueError(f"kernel must be one of {', '.join(KERNELS)} (got {kind!r})")


def kernel(sq: jax.Array, kind: str = "se", m52=False) -> jax.Array:
    """Correlation ``(...)`` from squared distances in length-scale units ``sq (...)``:
    ``se`` the squared exponential ``exp(-sq / 2)``, ``matern52`` the Matern 5/2
    ``(1 + r + r^2 / 3) exp(-r)`` with ``r = sqrt(5 sq)`` (Rasmussen & Williams Eq. 4.17;
    rougher: twice differentiable, where the squared exponential is infinitely smooth);
    ``auto`` either of the two, the Matern where ``m52`` (a bool array broadcasting with
    ``sq``; :func:`refine` chooses it by marginal likelihood)."""
    check_kernel(kind)
    if kind == "auto":
        return jnp.where(m52, kernel(sq, "matern52"), kernel(sq, "se"))
    if kind == "matern52":
        r = jnp.sqrt(5.0 * sq)
        return (1.0 + r + r * r / 3.0) * jnp.exp(-r)
    return jnp.exp(-0.5 * sq)


def fit(x: jax.Array, y: jax.Array, ell, prior=0.0, kind: str = "se", m52=False) -> Model:
    """The GP of signals ``y (H,)`` at ``x (H, P)`` (a non-finite ``y`` marks an empty slot)
    with length scales ``ell`` (a scalar or ``(P,)``), prior mean ``prior`` (standard
    deviations from the signals' mean) and correlation ``kind`` (:func:`kernel`; with
    ``auto``, the Matern where ``m52``, a traced () bool)."""
    ell = jnp.broadcast_to(jnp.asarray(ell, jnp.float32), x.shape[-1:])
    ok = jnp.isfinite(y)
    n = jnp.maximum(jnp.sum(ok), 1)
    y0 = jnp.where(ok, y, 0.0)
    mu = jnp.sum(y0) / n
    sd = jnp.sqrt(jnp.sum(jnp.where(ok, (y0 - mu) ** 2, 0.0)) / n)
    sd = jnp.where(sd > 0, sd, 1.0)
    prior = jnp.asarray(prior, jnp.float32)
    t = jnp.where(ok, (y0 - mu) / sd - prior, 0.0)  # standardised, less the prior; 0 if empty
    # an empty slot is an independent unit-variance point with target 0: no influence
    k = jnp.where(ok[:, None] & ok[None, :], kernel(_sq_dist(x, x, ell), kind, m52), 0.0) \
        + jnp.diag(jnp.where(ok, NOISE, 1.0))
    chol = cholesky(k)
    alpha = solve_upper(chol, solve_lower(chol, t[:, None]))[:, 0]
    # log marginal likelihood up to a constant (empty slots add log 1 = 0)
    lml = -0.5 * mm(t, alpha) - jnp.sum(jnp.log(jnp.diag(chol)))
    lml = jnp.where(jnp.isfinite(lml), lml, -jnp.inf)
    m52 = jnp.asarray(m52 if kind == "auto" else kind == "matern52", bool)
    return Model(x, ok, ell, chol, alpha, prior, mu, sd, lml, jnp.sum(ok) >= MIN_POINTS, m52)


def best_fit(x: jax.Array, y: jax.Array, ells: jax.Array, kind: str = "se") -> Model:
    """The fit with the highest log marginal likelihood among the length scales ``ells (C,
    P)`` (each candidate fitted once)."""
    models = jax.vmap(lambda e: fit(x, y, e, kind=kind))(ells)
    return jax.tree.map(lambda a: a[jnp.argmax(models.lml)], models)


def refine(x: jax.Array, y: jax.Array, ell: jax.Array, p, prior=0.0,
           kind: str = "se") -> Model:
    """ARD, one coordinate at a time: the best fit (prior mean ``prior``, see :func:`fit`)
    over ``ARD_SCALES`` for parameter ``p``'s length scale, the others kept at ``ell (P,)``;
    with ``kind="auto"`` over each scale with either correlation (14 fits instead of 7; the
    model's ``m52`` says which won). Without enough data for a model every candidate's
    likelihood is the same, and ``ell`` is kept as it is (with the squared exponential)."""
    cands = jnp.asarray(ARD_SCALES, jnp.float32)
    m52s = jnp.zeros(len(ARD_SCALES), bool)
    if kind == "auto":  # each scale with either correlation
        cands, m52s = jnp.concatenate([cands, cands]), jnp.concatenate([m52s, ~m52s])
    ells = jnp.broadcast_to(ell, cands.shape + ell.shape).at[:, p].set(cands)
    models = jax.vmap(lambda e, k: fit(x, y, e, prior, kind, k))(ells, m52s)
    lml = jnp.where(models.enough, models.lml,  # no model: the current scale's candidate
                    jnp.where(cands == ell[p], 0.0, -jnp.inf))
    return jax.tree.map(lambda a: a[jnp.argmax(lml)], models)


def predict(m: Model, z: jax.Array, kind: str = "se"):
    """``(mean (N,), var (N,), v (H, N))`` at ``z (N, P)``, standardised (the signal's units:
    ``mu + sd * mean``, ``sd^2 * var``); ``v = L^-1 k(X, z)``. Without a model: mean 0, var
    1; far from the data the mean tends to the prior mean."""
    ks = jnp.where(m.ok[None, :], kernel(_sq_dist(z, m.x, m.ell), kind, m.m52), 0.0)  # (N, H)
    v = solve_lower(m.chol, ks.T)  # (H, N)
    v = jnp.where(m.enough, v, 0.0)
    mean = jnp.where(m.enough, m.prior + mm(ks, m.alpha), 0.0)
    return mean, jnp.maximum(1.0 - jnp.sum(v * v, 0), 0.0), v


def posterior(x: jax.Array, y: jax.Array, z: jax.Array):
    """GP posterior at ``z (N, P)`` given points ``x (H, P)`` and signals ``y (H,)`` (both in
    unit coordinates; a non-finite ``y`` marks an empty slot), one length scale for all
    parameters, the one of ``LENGTH_SCALES`` with the highest marginal likelihood. Returns
    ``(mean (N,), std (N,), length_scale ())`` in the signal's units (mean 0, std 0 when fewer
    than ``MIN_POINTS`` slots are filled)."""
    ells = jnp.broadcast_to(jnp.asarray(LENGTH_SCALES, jnp.float32)[:, None],
                            (len(LENGTH_SCALES), x.shape[-1]))
    m = best_fit(x, y, ells)
    mean, var, _ = predict(m, z)
    return (jnp.where(m.enough, m.mu + m.sd * mean, 0.0),
            jnp.where(m.enough, m.sd * jnp.sqrt(var), 0.0), m.ell[0])


def ucb(x: jax.Array, y: jax.Array, z: jax.Array, kappa) -> jax.Array:
    """Upper confidence bound ``mean + kappa * std`` ``(N,)`` at ``z`` (see :func:`posterior`);
    all 0 without a model."""
    mean, std, _ = posterior(x, y, z)
    return mean + kappa * std


def batch_ucb(m: Model, z: jax.Array, allowed: jax.Array, kappa, b: int,
              kind: str = "se") -> jax.Array:
    """GP-BUCB: ``b`` distinct rows of ``z (N, P)`` (``(b,)`` int32, in the order picked),
    each the allowed, untaken candidate of highest ``mean + kappa * std`` (standardised), the
    std conditioned on the data and on the earlier picks as if observed (their outcomes do not
    change the mean; their variance does, by the rank-one updates of sequential conditioning).
    When no allowed candidate is left, the untaken ones in row order."""
    mean, var, v = predict(m, z, kind)
    n = z.shape[0]

    def pick(carry, j):
        var, u, taken = carry
        s = jnp.where(allowed & ~taken, mean + kappa * jnp.sqrt(var), -jnp.inf)
        i = jnp.where(jnp.any(allowed & ~taken), jnp.argmax(s), jnp.argmin(taken))
        # posterior covariance with the pick, given the data and the earlier picks
        kzi = kernel(_sq_dist(z, z[i][None], m.ell)[:, 0], kind, m.m52) - mm(v.T, v[:, i]) \
            - mm(u.T, u[:, i])
        c = kzi / jnp.sqrt(var[i] + NOISE)
        return (jnp.maximum(var - c * c, 0.0), u.at[j].set(c), taken.at[i].set(True)), i

    init = (var, jnp.zeros((b, n), jnp.float32), jnp.zeros(n, bool))
    return jax.lax.scan(pick, init, jnp.arange(b))[1].astype(jnp.int32)


@pytree.dataclass
class ScreenState:
    history: jax.Array  # (H, P) int32, the last H evaluated scenarios
    history_signal: jax.Array  # (H,) float32, their signals (-inf: empty slot)
    history_at: jax.Array  # () int32, evaluations written so far
    ell: jax.Array  # (P,) float32, the length scales (fractions of each range)


@dataclasses.dataclass(frozen=True)
class GPScreen:
    """Surrogate screening, a piece of a strategy: a GP fitted to the last ``size``
    evaluations (:meth:`record`) and to the strategy's best scenarios picks which candidates
    are asked (:meth:`pick`, GP-BUCB), its ``kernel`` (``se``, ``matern52`` or ``auto``) and
    length scales refined by marginal likelihood: during the first updates (as many as the
    parameters with two or more values) every such parameter's scale in turn, then one per
    update in turn. ``shape``: values per parameter."""

    size: int
    kernel: str
    shape: tuple[int, ...]

    def __post_init__(self):
        check_kernel(self.kernel)

    def init(self) -> ScreenState:
        P = len(self.shape)
        return ScreenState(jnp.zeros((self.size, P), jnp.int32),
                           jnp.full(self.size, -jnp.inf, jnp.float32), jnp.int32(0),
                           jnp.full(P, ARD_START, jnp.float32))

    def record(self, st: ScreenState, indices: jax.Array, signal: jax.Array) -> ScreenState:
        """The evaluations ``indices (B, P)``, ``signal (B,)`` into the ring buffer."""
        slots = (st.history_at + jnp.arange(indices.shape[0])) % self.size
        return dataclasses.replace(
            st, history=st.history.at[slots].set(indices),
            history_signal=st.history_signal.at[slots].set(
                jnp.where(jnp.isfinite(signal), signal, -jnp.inf)),
            history_at=jnp.minimum(st.history_at + indices.shape[0], 2**30))

    def pick(self, st: ScreenState, best: jax.Array, best_signal: jax.Array, told: jax.Array,
             idx: jax.Array, allowed: jax.Array, b: int, kappa, prior_mean):
        """GP-BUCB's ``(L, b)`` picks among each learner's candidates ``idx (L, C, P)`` (only
        ``allowed (L, C)`` ones while any is left), and the state with the refined length
        scales. ``best (N, P)``, ``best_signal (N,)`` (-inf: empty): the best scenarios found,
        data beside the history; ``told``: updates so far (which scales to refine)."""
        # the GP's data: the last evaluations and the best ones, a scenario counted once
        # (repeats are asked once the learner has a collision)
        hist = st.history
        dup = jnp.any(jnp.all(hist[:, None, :] == best[None, :, :], -1)
                      & jnp.isfinite(best_signal)[None, :], -1) \
            | equals_an_earlier(jnp.all(hist[:, None, :] == hist[None, :, :], -1))
        x = unit(jnp.concatenate([hist, best]), self.shape)
        y = jnp.concatenate([jnp.where(dup, -jnp.inf, st.history_signal), best_signal])
        movable = [p for p, n in enumerate(self.shape) if n > 1] or [0]

        def one_scale(p, ell):
            return refine(x, y, ell, p, prior_mean, self.kernel)

        def sweep():  # every movable parameter's scale in turn (a coordinate sweep), in a
            # loop: one GP refinement compiled, not one per parameter
            ps = jnp.asarray(movable)
            blank = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype),
                                 jax.eval_shape(one_scale, ps[0], st.ell))
            return jax.lax.fori_loop(0, len(movable), lambda i, m: one_scale(
                ps[i], jnp.where(i == 0, st.ell, m.ell)), blank)

        def round_robin():  # one parameter per update
            return one_scale(jnp.asarray(movable)[told % len(movable)], st.ell)

        # the first len(movable) updates sweep every scale, so all are fitted from the first
        # data on (a round robin alone leaves the last parameter at its starting scale for
        # len(movable) updates, while the rare spaces' first collisions come after 3-5)
        model = jax.lax.cond(told < len(movable), sweep, round_robin)
        z = unit(idx, self.shape)
        order = jax.vmap(lambda zl, al: batch_ucb(model, zl, al, kappa, b, self.kernel))(
            z, allowed)
        return order, dataclasses.replace(st, ell=model.ell)
