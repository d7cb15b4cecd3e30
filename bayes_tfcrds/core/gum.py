"""GUM-style uncertainty budget tables (JCGM 100:2008, with a JCGM 101 Monte Carlo check).

Generic on purpose: no physics of this project lives here. Analysis code fills a
:class:`Budget` with one :class:`Component` per input quantity or effect (ring-down noise,
H(f) parameters, t_cut choice, line-shape model, CMDS reference, pressure, temperature, ...),
each with its standard uncertainty u(x_i) and sensitivity coefficient c_i = df/dx_i, and
the budget gives the combined standard uncertainty (GUM Eq. 16, correlations included),
each component's share of u_c^2, the Welch-Satterthwaite effective degrees of freedom
(GUM Eq. G.2b), coverage factors and expanded uncertainties, and renders the table as
Markdown, CSV or a JSON-ready dict with the columns of JCGM 100 Table H.1.

Units: u(x_i) is in the unit of x_i (``Component.unit``); c_i is in output unit per unit of
x_i; contributions |c_i| u(x_i), u_c and U are in the output unit (``Budget.unit``).

Also here: :func:`normalized_error` (E_n, ISO/IEC 17043), :func:`ratio` (first-order
uncertainty of a/b) and :func:`monte_carlo_check` (propagation of a multivariate normal
through the model, JCGM 101 style, to validate a linear budget).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

__all__ = [
    "Component",
    "Budget",
    "COLUMNS",
    "normalized_error",
    "ratio",
    "dof_from_relative_u",
    "monte_carlo_check",
    "format_uncertainty",
    "format_value",
]

#: Column names of :meth:`Budget.to_rows` / CSV / Markdown (the columns of JCGM 100 Table H.1
#: plus the share of u_c^2 and a free-text note).
COLUMNS = (
    "quantity",
    "value",
    "standard uncertainty",
    "unit",
    "sensitivity coefficient",
    "contribution to u(y)",
    "share",
    "dof",
    "note",
)


def _finite(x: float, what: str) -> float:
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"{what} must be finite, got {x!r}")
    return x


@dataclass(frozen=True)
class Component:
    """One row of a budget: an input quantity X_i (or a pure effect) and its uncertainty.

    name: label, unique within a budget (used as key for correlations and shares).
    value: estimate x_i in ``unit``; None for effects without an estimate of their own
        (e.g. "ring-down noise", a model-choice term).
    u: standard uncertainty u(x_i) in ``unit`` (>= 0).
    sensitivity: c_i = df/dx_i in output unit per ``unit`` (sign kept: it matters for
        correlated inputs).
    unit: unit of x_i and u(x_i).
    dof: degrees of freedom of u(x_i); inf for a Type B evaluation taken as exact.
    note: Type A/B, assumed distribution, source.
    """

    name: str
    value: float | None
    u: float
    sensitivity: float
    unit: str = ""
    dof: float = math.inf
    note: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("Component.name must be a non-empty string")
        if self.value is not None:
            object.__setattr__(self, "value", _finite(self.value, f"{self.name}: value"))
        u = _finite(self.u, f"{self.name}: u")
        if u < 0:
            raise ValueError(f"{self.name}: standard uncertainty must be >= 0, got {u}")
        object.__setattr__(self, "u", u)
        object.__setattr__(
            self, "sensitivity", _finite(self.sensitivity, f"{self.name}: sensitivity")
        )
        dof = float(self.dof)
        if not dof > 0:  # also rejects nan
            raise ValueError(f"{self.name}: dof must be > 0 (inf allowed), got {dof}")
        object.__setattr__(self, "dof", dof)

    @property
    def contribution(self) -> float:
        """u_i(y) = |c_i| u(x_i), in the output unit (GUM 5.1.3)."""
        return abs(self.sensitivity) * self.u


@dataclass(frozen=True)
class Budget:
    """Uncertainty budget for one output quantity Y = f(X_1, ..., X_N) (JCGM 100 Sec. 5).

    quantity: name of the measurand; value: its estimate y in ``unit``;
    components: the rows; correlations: r(x_i, x_j) keyed by a pair of component names
    (either order; GUM Eq. 16 / C.3.6). Unlisted pairs are uncorrelated. The correlation
    matrix is checked to be positive semi-definite, since otherwise u_c^2 could come out
    negative.
    """

    quantity: str
    value: float
    unit: str
    components: tuple[Component, ...]
    correlations: dict[tuple[str, str], float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "value", _finite(self.value, "Budget.value"))
        comps = tuple(self.components)
        if not comps:
            raise ValueError("a budget needs at least one component")
        for c in comps:
            if not isinstance(c, Component):
                raise TypeError(f"components must be Component instances, got {type(c)}")
        names = [c.name for c in comps]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"duplicate component names: {dupes}")
        object.__setattr__(self, "components", comps)

        index = {n: i for i, n in enumerate(names)}
        norm: dict[tuple[str, str], float] = {}
        for key, r in dict(self.correlations).items():
            a, b = key
            for n in (a, b):
                if n not in index:
                    raise ValueError(f"correlation names unknown component {n!r}")
            if a == b:
                raise ValueError(f"self-correlation given for {a!r}")
            r = _finite(r, f"r({a}, {b})")
            if abs(r) > 1.0:
                raise ValueError(f"|r({a}, {b})| = {abs(r)} > 1")
            k = (a, b) if index[a] < index[b] else (b, a)
            if k in norm and norm[k] != r:
                raise ValueError(f"conflicting correlations given for {k}")
            norm[k] = r
        object.__setattr__(self, "correlations", norm)

        R = self.correlation_matrix()
        if np.linalg.eigvalsh(R).min() < -1e-10:
            raise ValueError("correlation matrix is not positive semi-definite")

    # --- propagation -------------------------------------------------------------------
    def correlation_matrix(self) -> np.ndarray:
        """N x N matrix of r(x_i, x_j), component order, ones on the diagonal."""
        idx = {c.name: i for i, c in enumerate(self.components)}
        R = np.eye(len(self.components))
        for (a, b), r in self.correlations.items():
            R[idx[a], idx[b]] = R[idx[b], idx[a]] = r
        return R

    def _signed(self) -> np.ndarray:
        """c_i u(x_i) with sign, output unit."""
        return np.array([c.sensitivity * c.u for c in self.components])

    @property
    def combined_u(self) -> float:
        """u_c(y), output unit: GUM Eq. 16, u_c^2 = sum_ij c_i c_j u_i u_j r_ij."""
        s = self._signed()
        var = float(s @ self.correlation_matrix() @ s)
        return math.sqrt(max(var, 0.0))  # PSD R: only rounding can make var < 0

    def shares(self) -> dict[str, float]:
        """Share of u_c^2 per component name; the shares sum to 1.

        With correlations the share of component i is c_i u_i (sum_j c_j u_j r_ij) / u_c^2,
        i.e. its own variance plus half of each covariance term it takes part in. It can be
        negative (an anti-correlated input that reduces u_c) or exceed 1. Uncorrelated
        inputs give the usual (c_i u_i)^2 / u_c^2. nan for every component if u_c = 0.
        """
        s = self._signed()
        var = float(s @ self.correlation_matrix() @ s)
        if var <= 0.0:
            return {c.name: math.nan for c in self.components}
        part = s * (self.correlation_matrix() @ s) / var
        return {c.name: float(p) for c, p in zip(self.components, part)}

    @property
    def effective_dof(self) -> float:
        """Welch-Satterthwaite nu_eff = u_c^4 / sum_i u_i(y)^4 / nu_i (GUM Eq. G.2b).

        Not rounded (GUM G.6.4 truncates it only for the t-table look-up; see
        :meth:`coverage_factor`). inf if every contributing dof is infinite. The formula
        assumes independent inputs; with correlations it is computed the same way (u_c
        from Eq. 16) but is only indicative.
        """
        den = sum(c.contribution**4 / c.dof for c in self.components if math.isfinite(c.dof))
        if den == 0.0:
            return math.inf
        return self.combined_u**4 / den

    def coverage_factor(self, p: float = 0.95, truncate: bool = True) -> float:
        """k_p = t_p(nu_eff): two-sided Student-t quantile for coverage probability p.

        truncate=True follows GUM G.6.4 (nu_eff truncated to the next lower integer, which
        gives the slightly larger, conservative k); infinite nu_eff gives the normal k.
        """
        if not 0.0 < p < 1.0:
            raise ValueError(f"coverage probability must be in (0, 1), got {p}")
        nu = self.effective_dof
        if not nu > 0:
            raise ValueError(f"effective dof is {nu}; no coverage factor (u_c = 0?)")
        if math.isinf(nu):
            return float(stats.norm.ppf(0.5 + p / 2.0))
        if truncate and nu >= 1.0:
            nu = math.floor(nu)
        return float(stats.t.ppf(0.5 + p / 2.0, nu))

    def expanded(self, k: float = 2.0) -> float:
        """Expanded uncertainty U = k u_c(y), output unit (GUM 6.2.1)."""
        return float(k) * self.combined_u

    def in_units(self, conversions: dict[str, tuple[str, float]]) -> Budget:
        """The same budget with units converted, e.g. {"Hz/m": ("cm^-2", 1/(100 c))}.

        ``conversions`` maps a unit to (new unit, factor: new = factor x old). Inputs in a listed
        unit get value and u scaled, the output too, and every c_i follows (c_i x f_out/f_in);
        shares, dof and correlations are unchanged (dimensionless).
        """

        def conv(unit):
            return conversions.get(unit, (unit, 1.0))

        out_unit, f_out = conv(self.unit)
        comps = []
        for c in self.components:
            unit, f_in = conv(c.unit)
            comps.append(
                replace(
                    c,
                    value=None if c.value is None else c.value * f_in,
                    u=c.u * f_in,
                    unit=unit,
                    sensitivity=c.sensitivity * f_out / f_in,
                )
            )
        return Budget(
            self.quantity, self.value * f_out, out_unit, tuple(comps), dict(self.correlations)
        )

    # --- reporting ---------------------------------------------------------------------
    def to_rows(self) -> list[dict]:
        """One dict per component keyed by :data:`COLUMNS`, raw (unformatted) numbers.

        'standard uncertainty' and 'value' are in 'unit' (of x_i); 'sensitivity
        coefficient' in output unit per x_i unit; 'contribution to u(y)' in output unit;
        'share' is the fraction of u_c^2 (see :meth:`shares`).
        """
        sh = self.shares()
        return [
            {
                "quantity": c.name,
                "value": c.value,
                "standard uncertainty": c.u,
                "unit": c.unit,
                "sensitivity coefficient": c.sensitivity,
                "contribution to u(y)": c.contribution,
                "share": sh[c.name],
                "dof": c.dof,
                "note": c.note,
            }
            for c in self.components
        ]

    def to_markdown(self) -> str:
        """Markdown table, rounded for reading.

        U to 2 significant digits, value to the same decimal place as its u; followed by u_c, nu_eff
        and expanded uncertainties.
        """
        head = [
            "quantity",
            "value",
            "standard uncertainty",
            "unit",
            "sensitivity coefficient",
            f"contribution to u(y) / {self.unit}",
            "share",
            "dof",
            "note",
        ]
        lines = [
            "| " + " | ".join(head) + " |",
            "|"
            + "|".join(["---", "---:", "---:", "---", "---:", "---:", "---:", "---:", "---"])
            + "|",
        ]
        for row in self.to_rows():
            cells = [
                row["quantity"],
                "—"
                if row["value"] is None
                else format_value(row["value"], row["standard uncertainty"]),
                format_uncertainty(row["standard uncertainty"]),
                row["unit"],
                f"{row['sensitivity coefficient']:.4g}",
                format_uncertainty(row["contribution to u(y)"]),
                "—" if math.isnan(row["share"]) else f"{100.0 * row['share']:.1f} %",
                _format_dof(row["dof"]),
                row["note"],
            ]
            lines.append("| " + " | ".join(_md_escape(str(x)) for x in cells) + " |")
        uc = self.combined_u
        nu = self.effective_dof
        lines += [
            "",
            f"{self.quantity} = {format_value(self.value, uc)} {self.unit}; combined standard "
            f"uncertainty u_c = {format_uncertainty(uc)} {self.unit}; effective dof nu_eff = "
            f"{_format_dof(nu)}.",
            f"Expanded uncertainty U (k = 2) = {format_uncertainty(self.expanded(2.0))} "
            f"{self.unit}.",
        ]
        if nu > 0:
            k95 = self.coverage_factor(0.95)
            lines.append(
                f"Expanded uncertainty U_95 (k = t_95(nu_eff) = {k95:.3f}) = "
                f"{format_uncertainty(self.expanded(k95))} {self.unit}."
            )
        lines.append(
            f"Sensitivity coefficients in {self.unit} per unit of the input; share = fraction of "
            "u_c^2."
        )
        if self.correlations:
            pairs = ", ".join(f"r({a}, {b}) = {r:g}" for (a, b), r in self.correlations.items())
            lines.append(f"Correlations: {pairs} (nu_eff only indicative).")
        return "\n".join(lines) + "\n"

    def to_csv(self) -> str:
        """CSV (stdlib csv): a header line of :data:`COLUMNS` and one line per component.

        Full precision (repr of floats); empty value for None; 'inf' dof.
        """
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(COLUMNS)
        for row in self.to_rows():
            w.writerow(
                [
                    ""
                    if row[k] is None
                    else (repr(row[k]) if isinstance(row[k], float) else row[k])
                    for k in COLUMNS
                ]
            )
        return buf.getvalue()

    def to_dict(self) -> dict:
        """JSON-ready dict (strict JSON.

        Infinite dof become the string "inf", undefined shares None, correlations a list of {a, b,
        r}).
        """
        sh = self.shares()
        return {
            "quantity": self.quantity,
            "value": self.value,
            "unit": self.unit,
            "components": [
                {
                    "name": c.name,
                    "value": c.value,
                    "u": c.u,
                    "unit": c.unit,
                    "sensitivity": c.sensitivity,
                    "contribution": c.contribution,
                    "share": _json_float(sh[c.name]),
                    "dof": _json_float(c.dof),
                    "note": c.note,
                }
                for c in self.components
            ],
            "correlations": [{"a": a, "b": b, "r": r} for (a, b), r in self.correlations.items()],
            "combined_u": self.combined_u,
            "effective_dof": _json_float(self.effective_dof),
            "expanded_k2": self.expanded(2.0),
            "k_95": self.coverage_factor(0.95) if self.effective_dof > 0 else None,
        }


def dof_from_relative_u(relative_u: float) -> float:
    """Degrees of freedom of a Type B u from the judged relative uncertainty of u (GUM Eq. G.3).

    nu = (1/2) (Delta u / u)^-2: a u judged reliable to 25 % has 8 dof, to 50 % 2 dof, to 10 %
    50 dof; 0 gives inf (u taken as exact).
    """
    r = float(relative_u)
    if not r >= 0:
        raise ValueError(f"relative uncertainty of u must be >= 0, got {r}")
    return math.inf if r == 0.0 else 0.5 / (r * r)


# --- comparison helpers ----------------------------------------------------------------
def normalized_error(x: float, U_x: float, y: float, U_y: float) -> float:
    """E_n = (x - y) / sqrt(U_x^2 + U_y^2) with expanded (k = 2) uncertainties (ISO/IEC 17043).

    |E_n| <= 1 means agreement. x, y, U_x, U_y in one unit.
    """
    den = math.hypot(float(U_x), float(U_y))
    if not den > 0:
        raise ValueError("U_x and U_y cannot both be zero")
    return (float(x) - float(y)) / den


def ratio(a: float, u_a: float, b: float, u_b: float, corr: float = 0.0) -> tuple[float, float]:
    """r = a/b and its first-order standard uncertainty.

    GUM Eq. 16 with c_a = 1/b, c_b = -a/b^2 and r(a, b) = corr. Written with absolute
    sensitivities so a = 0 works; u_r is in the unit of a/b.
    """
    a, u_a, b, u_b, corr = map(float, (a, u_a, b, u_b, corr))
    if b == 0.0:
        raise ValueError("b must be non-zero")
    if abs(corr) > 1.0:
        raise ValueError(f"|corr| must be <= 1, got {corr}")
    sa = u_a / b
    sb = -a * u_b / b**2
    var = sa * sa + sb * sb + 2.0 * corr * sa * sb
    return a / b, math.sqrt(max(var, 0.0))


def monte_carlo_check(
    f: Callable[..., np.ndarray], means: Iterable[float], cov, rng, n: int = 100_000
) -> tuple[float, float]:
    """Propagate X ~ N(means, cov) through f by sampling (JCGM 101 style): (mean, sd) of Y.

    f is vectorised and called as f(x_1, ..., x_N) with one array of n draws per input
    (in the order of ``means``). cov is the N x N covariance matrix in the inputs' units
    (may be singular, e.g. for fully correlated inputs). rng is a numpy Generator (or a
    seed). Used to check a linear budget: a sd far from u_c flags a non-linear model or a
    wrong sensitivity. sd uses ddof = 1.
    """
    mu = np.atleast_1d(np.asarray(means, dtype=float))
    if mu.ndim != 1:
        raise ValueError("means must be 1-d")
    C = np.atleast_2d(np.asarray(cov, dtype=float))
    if C.shape != (mu.size, mu.size):
        raise ValueError(f"cov must be {mu.size} x {mu.size}, got {C.shape}")
    if not np.allclose(C, C.T):
        raise ValueError("cov must be symmetric")
    if int(n) < 2:
        raise ValueError("n must be >= 2")
    gen = np.random.default_rng(rng)
    x = gen.multivariate_normal(mu, C, size=int(n), check_valid="raise")
    y = np.asarray(f(*x.T), dtype=float)
    if y.shape != (int(n),):
        raise ValueError(f"f must return one value per draw, shape ({n},); got {y.shape}")
    if not np.all(np.isfinite(y)):
        raise ValueError("f returned non-finite values")
    return float(y.mean()), float(y.std(ddof=1))


# --- number formatting -----------------------------------------------------------------
def _lead_exponent(u: float, digits: int) -> int:
    """Decimal exponent of the leading digit of |u| after rounding to `digits` figures."""
    e = math.floor(math.log10(abs(u)))
    r = round(abs(u), digits - 1 - e)
    if r > 0 and math.floor(math.log10(r)) > e:  # e.g. 9.96 -> 10
        e += 1
    return e


def _fixed_ok(e: int) -> bool:
    return -4 <= e < 6


def format_uncertainty(u: float, digits: int = 2) -> str:
    """u rounded to `digits` significant digits (GUM 7.2.6).

    Fixed-point for 1e-4 <= u < 1e6, else scientific: 0.028868 -> '0.029', 1.1547e-6 -> '1.2e-06'.
    """
    u = float(u)
    if u == 0.0 or not math.isfinite(u):
        return f"{u:g}"
    e = _lead_exponent(u, digits)
    if _fixed_ok(e):
        dec = digits - 1 - e
        return f"{round(u, dec) + 0.0:.{max(dec, 0)}f}"
    return f"{u:.{digits - 1}e}"


def format_value(x: float, u: float, digits: int = 2) -> str:
    """x rounded to the decimal place of the last significant digit of u (GUM 7.2.6).

    u as printed by :func:`format_uncertainty`; 6 significant digits if u is 0 or not finite.
    """
    x, u = float(x), float(u)
    if u == 0.0 or not math.isfinite(u) or not math.isfinite(x):
        return f"{x:.6g}"
    e = _lead_exponent(u, digits)
    last = e - digits + 1  # place of u's last digit, 10**last
    if _fixed_ok(e):
        return f"{round(x, -last) + 0.0:.{max(-last, 0)}f}"
    if x == 0.0:
        return "0"
    ex = math.floor(math.log10(abs(x)))
    if ex >= last:
        return f"{x:.{ex - last}e}"
    return f"{x / 10.0**e:.{digits - 1}f}e{e:+03d}"  # |x| below u's last digit


def _format_dof(nu: float) -> str:
    if math.isinf(nu):
        return "∞"
    return f"{nu:.3g}"


def _md_escape(s: str) -> str:
    return s.replace("|", "\\|").replace("\n", " ")


def _json_float(x: float) -> float | str | None:
    if math.isnan(x):
        return None
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return x
