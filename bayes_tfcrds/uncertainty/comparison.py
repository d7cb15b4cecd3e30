"""Statistics of an interlaboratory comparison (CCQM style, Cox 2002 Procedure A generalised).

n results x_i of one measurand with a covariance matrix V (standard uncertainties u_i and the
declared correlations r_ij of results that share inputs, e.g. the same H or manometer). The
reference value is a linear function of the results plus an independent part,

    x_ref = a^T x + c,   u_c = standard uncertainty of c (independent of every x_i),

which covers the choices of a comparison: the generalised-least-squares weighted mean
(a = V^-1 1 / (1^T V^-1 1), c = 0), one laboratory's result (a = e_j), a stated value
(a = 0, c with its u), and the random-effects consensus for results that scatter beyond their
u: the GLS mean under Sigma = V + tau^2 I, tau the dark uncertainty (DerSimonian-Laird, REML or
ML; optional Knapp-Hartung interval; see :mod:`.random_effects`). Every statistic then follows
from V (from Sigma for the random-effects consensus):

    d = x - 1 x_ref = B x - 1 c,  B = I - 1 a^T,   cov(d) = B V B^T + u_c^2 1 1^T,

so the correlation of x_i with x_ref is accounted for in u(d_i) whatever the reference (for
the weighted mean of independent results u^2(d_i) = u_i^2 - u_ref^2, Cox 2002 Procedure A).

All values are in one unit (the caller's); results are frozen dataclasses.

Cox 2002: M. G. Cox, "The evaluation of key comparison data", Metrologia 39 (2002) 589-595.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

from bayes_tfcrds.uncertainty.random_effects import (
    ESTIMATORS,
    cochran_q,
    coverage_interval,
    dark_uncertainty,
    knapp_hartung_factor,
)

#: coverage factor of the expanded uncertainties U(d) and of E_n
K_EXPANDED = 2.0
#: significance level of the chi-squared consistency test
ALPHA = 0.05


@dataclass(frozen=True)
class Reference:
    """How the reference value is chosen.

    kind: 'weighted-mean' (GLS mean of all results), 'laboratory' (the result of ``lab``),
    'value' (a stated ``value`` with standard uncertainty ``u``, independent of the results),
    or 'random-effects' (the consensus with dark uncertainty tau by ``estimator``, 'DL', 'REML'
    or 'ML'; ``knapp_hartung`` 'standard' scales its u by sqrt(q) and takes the interval from t
    with n - 1 dof, 'modified' by sqrt(max(q, 1)), which never gives a u below the plain one).
    value and u in the unit of the comparison.
    """

    kind: str = "weighted-mean"
    lab: str | None = None
    value: float | None = None
    u: float | None = None
    estimator: str = "REML"
    knapp_hartung: str = ""  # "", "standard" or "modified"


@dataclass(frozen=True)
class ReferenceValue:
    """The reference value x_ref, its standard uncertainty and the weights a_i of the results.

    tau is the dark uncertainty of a random-effects consensus (0 otherwise), interval the 95 %
    coverage interval (normal quantile, or Student's t with ``dof`` for Knapp-Hartung; dof None
    means infinite), all in the unit of the comparison. ``kh_q`` is the Knapp-Hartung q (None
    without the adjustment): q < 1 shrinks u below the plain random-effects u in the standard form.
    """

    method: str
    value: float
    u: float
    weights: tuple
    tau: float = 0.0
    interval: tuple = ()
    dof: float | None = None
    kh_q: float | None = None


@dataclass(frozen=True)
class Consistency:
    """Chi-squared test of the results about their GLS weighted mean.

    chi2 = r^T V^-1 r (r the residuals), dof = n - 1, p = P(chi2_dof > chi2), Birge ratio
    R_B = sqrt(chi2 / dof); passed when p >= ALPHA (Cox 2002, Procedure A).
    """

    chi2: float
    dof: int
    p_value: float
    birge_ratio: float
    passed: bool
    alpha: float = ALPHA


@dataclass(frozen=True)
class Equivalence:
    """Degree of equivalence of one result: d = x - x_ref, u(d), U(d) = k u(d), E_n and zeta.

    zeta = d / u(d) and E_n = d / U(d); both are None where u(d) = 0 (the reference laboratory
    against itself).
    """

    lab: str
    d: float
    u: float
    U: float
    en: float | None
    zeta: float | None


@dataclass(frozen=True)
class PairEquivalence:
    """Degree of equivalence of two results: d_ab = x_a - x_b, u, U = k u and E_n = d/U."""

    lab_a: str
    lab_b: str
    d: float
    u: float
    U: float
    en: float | None


@dataclass(frozen=True)
class Comparison:
    """A comparison evaluated: inputs, reference value, consistency and degrees of equivalence."""

    quantity: str
    unit: str
    labs: tuple
    values: tuple
    u: tuple
    correlation: tuple
    reference: ReferenceValue
    consistency: Consistency
    equivalence: tuple
    pairs: tuple
    k: float = K_EXPANDED

    def to_dict(self) -> dict:
        """A JSON-ready dict of every field (nested dataclasses as dicts)."""
        return asdict(self)


def covariance_matrix(u, correlation) -> np.ndarray:
    """V_ij = r_ij u_i u_j, in the unit squared; refuses a matrix that is not positive definite.

    Parameters
    ----------
    u : array (n,)
        Standard uncertainties, all > 0.
    correlation : array (n, n)
        Symmetric, unit diagonal, |r_ij| <= 1.
    """
    u = np.asarray(u, dtype=float)
    r = np.asarray(correlation, dtype=float)
    if np.any(~np.isfinite(u)) or np.any(u <= 0):
        raise ValueError("every standard uncertainty must be finite and > 0")
    if not np.allclose(r, r.T) or not np.allclose(np.diag(r), 1.0) or np.any(np.abs(r) > 1):
        raise ValueError("correlations must be symmetric, in [-1, 1], with a unit diagonal")
    if np.linalg.eigvalsh(r).min() <= 1e-12:
        raise ValueError(
            "the declared correlations are not a valid correlation matrix (not positive "
            "definite); check the pairs for contradictions, e.g. r = 1 twice with a third lab"
        )
    return r * np.outer(u, u)


def gls_weights(cov) -> np.ndarray:
    """Weights of the GLS weighted mean, a = V^-1 1 / (1^T V^-1 1) (they sum to 1).

    For independent results a_i = u_i^-2 / sum_j u_j^-2 (Cox 2002, Procedure A).
    """
    vinv_1 = np.linalg.solve(cov, np.ones(len(cov)))
    return vinv_1 / vinv_1.sum()


def weighted_mean(x, cov) -> ReferenceValue:
    """GLS weighted mean of results with covariance ``cov``: the best linear unbiased estimate.

    x_ref = a^T x with u^2(x_ref) = a^T V a = 1 / (1^T V^-1 1); for independent results the
    inverse-variance mean with u^2 = 1 / sum u_i^-2 (Cox 2002, Procedure A).
    """
    return reference_value(x, cov, gls_weights(cov), 0.0, 0.0, "weighted mean")


def consistency(x, cov, alpha: float = ALPHA) -> Consistency:
    """Chi-squared test of the results about their GLS mean, with the Birge ratio.

    Parameters
    ----------
    x : array (n,), n >= 2
        Results, any unit.
    cov : array (n, n)
        Their covariance matrix, unit squared.
    """
    x = np.asarray(x, dtype=float)
    chi2 = cochran_q(x, cov)
    dof = x.size - 1
    p = float(stats.chi2.sf(chi2, dof))
    return Consistency(chi2, dof, p, float(np.sqrt(chi2 / dof)), p >= alpha, alpha)


def reference_weights(labs, cov, reference: Reference) -> tuple[np.ndarray, float, float]:
    """The linear form of x_ref: weights a (n,), offset c and its independent u_c."""
    n = len(labs)
    if reference.kind == "weighted-mean":
        return gls_weights(cov), 0.0, 0.0
    if reference.kind == "laboratory":
        if reference.lab not in labs:
            raise ValueError(f"reference laboratory {reference.lab!r} is not among {list(labs)}")
        return np.eye(n)[list(labs).index(reference.lab)], 0.0, 0.0
    if reference.kind == "value":
        if reference.value is None or reference.u is None or not reference.u >= 0:
            raise ValueError("a stated reference value needs a value and a standard u >= 0")
        return np.zeros(n), float(reference.value), float(reference.u)
    raise ValueError(f"unknown reference kind {reference.kind!r}")


def reference_value(x, cov, a, c: float, u_c: float, method: str) -> ReferenceValue:
    """x_ref = a^T x + c with u^2 = a^T V a + u_c^2, and its normal 95 % interval."""
    a = np.asarray(a, dtype=float)
    value = float(a @ np.asarray(x) + c)
    u = float(np.sqrt(a @ cov @ a + u_c**2))
    return ReferenceValue(method, value, u, tuple(a), interval=coverage_interval(value, u, None))


KNAPP_HARTUNG = ("", "standard", "modified")


def random_effects_reference(x, cov, estimator: str, knapp_hartung: str = ""):
    """The random-effects consensus and Sigma = V + tau^2 I, the covariance its DoE use.

    x_ref is the GLS mean under Sigma; u^2 = 1 / (1^T Sigma^-1 1), times q ('standard'
    Knapp-Hartung, as metafor's ``test="knha"``) or max(q, 1) ('modified') when asked, with the
    interval from t_{n-1}.
    """
    if estimator not in ESTIMATORS:
        raise ValueError(f"unknown estimator {estimator!r}; use one of {', '.join(ESTIMATORS)}")
    if knapp_hartung not in KNAPP_HARTUNG:
        raise ValueError(f"knapp_hartung must be one of {KNAPP_HARTUNG}, got {knapp_hartung!r}")
    x = np.asarray(x, dtype=float)
    tau = dark_uncertainty(x, cov, estimator)
    sigma = cov + tau**2 * np.eye(x.size)
    a = gls_weights(sigma)
    value = float(a @ x)
    u = float(np.sqrt(a @ sigma @ a))
    dof = q = None
    method = f"random effects ({estimator})"
    if knapp_hartung:
        q = knapp_hartung_factor(x, sigma) ** 2
        u *= float(np.sqrt(max(q, 1.0) if knapp_hartung == "modified" else q))
        dof = float(x.size - 1)
        kind = "modified Knapp-Hartung" if knapp_hartung == "modified" else "Knapp-Hartung"
        method = f"random effects ({estimator}, {kind})"
    ref = ReferenceValue(method, value, u, tuple(a), tau, coverage_interval(value, u, dof), dof, q)
    return ref, sigma


def degrees_of_equivalence(x, cov, a, c: float = 0.0, u_c: float = 0.0):
    """d_i = x_i - x_ref and u(d_i) for x_ref = a^T x + c (c independent, uncertainty u_c).

    cov(d) = B V B^T + u_c^2 1 1^T with B = I - 1 a^T, so a result's share in x_ref (its weight,
    its correlations with the others) lowers u(d_i) as it must. Returns (d, u_d), unit of x.
    """
    x = np.asarray(x, dtype=float)
    a = np.asarray(a, dtype=float)
    b = np.eye(x.size) - np.outer(np.ones(x.size), a)
    cov_d = b @ cov @ b.T + u_c**2
    d = b @ x - c
    return d, np.sqrt(np.clip(np.diag(cov_d), 0.0, None))


def pairwise_differences(x, cov) -> tuple[np.ndarray, np.ndarray]:
    """d_ij = x_i - x_j and u^2(d_ij) = u_i^2 + u_j^2 - 2 V_ij (declared correlations), (n, n)."""
    x = np.asarray(x, dtype=float)
    var = np.diag(cov)
    u2 = var[:, None] + var[None, :] - 2.0 * cov
    return x[:, None] - x[None, :], np.sqrt(np.clip(u2, 0.0, None))


def _method_name(reference: Reference) -> str:
    """How the reference value was formed, for tables: 'weighted mean', 'laboratory X', ..."""
    if reference.kind == "laboratory":
        return f"laboratory {reference.lab}"
    return "weighted mean" if reference.kind == "weighted-mean" else "stated value"


def _ratio_or_none(d: float, u: float) -> float | None:
    return float(d / u) if u > 0 else None


def compare(
    labs,
    x,
    u,
    correlation=None,
    reference: Reference = Reference(),
    quantity: str = "",
    unit: str = "",
) -> Comparison:
    """Evaluate a comparison: reference value, consistency, degrees of equivalence, pairs.

    Parameters
    ----------
    labs : sequence of str
        Names of the n >= 2 results, all different.
    x, u : array (n,)
        Values and standard uncertainties in one unit (``unit``).
    correlation : array (n, n), optional
        Declared correlation matrix of the results (identity when None).
    reference : Reference
        Weighted mean (default), one laboratory, a stated value with u, or the random-effects
        consensus. For the last, the degrees of equivalence use Sigma = V + tau^2 I: a result's
        d is judged against its own u and the dark uncertainty that the consensus model gives
        every laboratory (tau taken as known; its own uncertainty is not propagated); pairs use
        V alone.
    """
    labs = tuple(str(lab) for lab in labs)
    x = np.asarray(x, dtype=float)
    if x.size < 2 or len(labs) != x.size:
        raise ValueError("a comparison needs at least two results, one name each")
    twice = sorted({lab for lab in labs if labs.count(lab) > 1})
    if twice:
        raise ValueError(
            f"results need different names; {', '.join(repr(t) for t in twice)} appear more "
            "than once (label budget.json results with LABEL=PATH, or rename the CSV rows)"
        )
    r = np.eye(x.size) if correlation is None else np.asarray(correlation, dtype=float)
    cov = covariance_matrix(u, r)
    if reference.kind == "random-effects":
        ref, cov_doe = random_effects_reference(
            x, cov, reference.estimator, reference.knapp_hartung
        )
        a, c, u_c = np.asarray(ref.weights), 0.0, 0.0
    else:
        a, c, u_c = reference_weights(labs, cov, reference)
        ref, cov_doe = reference_value(x, cov, a, c, u_c, _method_name(reference)), cov
    d, u_d = degrees_of_equivalence(x, cov_doe, a, c, u_c)
    eq = tuple(
        Equivalence(
            lab,
            float(di),
            float(ui),
            float(K_EXPANDED * ui),
            _ratio_or_none(di, K_EXPANDED * ui),
            _ratio_or_none(di, ui),
        )
        for lab, di, ui in zip(labs, d, u_d)
    )
    return Comparison(
        quantity=quantity,
        unit=unit,
        labs=labs,
        values=tuple(float(v) for v in x),
        u=tuple(float(v) for v in np.asarray(u, dtype=float)),
        correlation=tuple(tuple(float(v) for v in row) for row in r),
        reference=ref,
        consistency=consistency(x, cov),
        equivalence=eq,
        pairs=_pairs(labs, x, cov),
    )


def _pairs(labs, x, cov) -> tuple:
    """Every unordered pair (a before b in input order) with d_ab, u, U and E_n."""
    d, u = pairwise_differences(x, cov)
    n = len(labs)
    return tuple(
        PairEquivalence(
            labs[i],
            labs[j],
            float(d[i, j]),
            float(u[i, j]),
            float(K_EXPANDED * u[i, j]),
            _ratio_or_none(d[i, j], K_EXPANDED * u[i, j]),
        )
        for i in range(n)
        for j in range(i + 1, n)
    )
