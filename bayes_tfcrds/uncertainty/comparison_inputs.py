"""Inputs of a comparison: budget.json files, a CSV of results from elsewhere, correlations.

Every result is converted to the one unit of the compared quantity (S in cm/molecule at
T_ref = 296 K, A in cm^-2, A/A_ref dimensionless). Errors name the file, line and column and say
what to write instead.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayes_tfcrds.core.constants import line_area_to_cm2

#: quantity -> (unit of the comparison, accepted units -> factor into it, SI unit, factor to SI)
QUANTITIES = {
    "intensity": (
        "cm/molecule",
        {"cm/molecule": 1.0, "cm molecule-1": 1.0, "cm/molec": 1.0, "m/molecule": 100.0},
        "m/molecule",
        1e-2,
    ),
    "line_area": (
        "cm^-2",
        {"cm^-2": 1.0, "cm-2": 1.0, "m^-2": 1e-4, "m-2": 1e-4, "Hz/m": float(line_area_to_cm2(1))},
        "Hz/m",
        1.0 / float(line_area_to_cm2(1)),
    ),
    "ratio": ("1", {"1": 1.0, "": 1.0}, None, None),
    # any other measurand, from CSV files only: compared in the unit the rows state (one unit)
    "other": (None, {}, None, None),
}

#: budget.json key of each quantity
BUDGET_KEYS = {"intensity": "intensity", "line_area": "line_area", "ratio": "ratio"}


class ComparisonInputError(ValueError):
    """A comparison input that cannot be used; the message names the file and field."""


@dataclass(frozen=True)
class LabResult:
    """One laboratory's result in the comparison's unit: value, standard u, dof (inf if none)."""

    lab: str
    value: float
    u: float
    source: str
    dof: float = math.inf
    unit: str = ""


def unit_of(quantity: str) -> str | None:
    """The unit every result of ``quantity`` is compared in (None for 'other': the CSV's)."""
    return _spec(quantity)[0]


def common_unit(results, quantity: str) -> str:
    """The one unit of the compared results; refuses 'other' results in different units."""
    if quantity != "other":
        return unit_of(quantity)
    units = sorted({r.unit for r in results})
    if len(units) != 1:
        raise ComparisonInputError(
            f"results of quantity 'other' are compared in the unit they state, and these state "
            f"{', '.join(repr(u) for u in units)}; convert them to one unit"
        )
    return units[0]


def _spec(quantity: str):
    if quantity not in QUANTITIES:
        raise ComparisonInputError(
            f"unknown quantity {quantity!r}; choose one of {', '.join(QUANTITIES)}"
        )
    return QUANTITIES[quantity]


def read_result(spec: str, quantity: str) -> list:
    """The results named by one command-line RESULT: ``[LABEL=]PATH``.

    A ``.csv`` gives one result per row; anything else is a budget.json (or a budget folder)
    whose label defaults to its folder's name.
    """
    label, _, path = ("", "", spec) if Path(spec).exists() else spec.partition("=")
    if not path:
        label, path = "", spec
    p = Path(path)
    if p.suffix.lower() == ".csv":
        if label:
            raise ComparisonInputError(f"{spec}: a CSV names its laboratories in its lab column")
        return read_results_csv(p, quantity)
    if p.is_dir():
        p = p / "budget.json"
    return [read_budget(p, label or p.resolve().parent.name, quantity)]


def read_budget(path, lab: str, quantity: str) -> LabResult:
    """The ``quantity`` entry of a budget.json written by ``bayes-tfcrds budget``."""
    path = Path(path)
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ComparisonInputError(f"{path}: cannot read a budget.json ({exc})") from None
    _spec(quantity)
    if quantity not in BUDGET_KEYS:
        raise ComparisonInputError(
            f"{path}: a budget.json has no {quantity!r} quantity; use one of "
            f"{', '.join(BUDGET_KEYS)}, or give results of other measurands as a CSV"
        )
    key = BUDGET_KEYS[quantity]
    if summary.get("status", "ok") != "ok":
        raise ComparisonInputError(
            f"{path}: the budget failed its gates ({summary.get('status')}); rerun it before "
            "comparing"
        )
    entry = summary.get(key)
    if not isinstance(entry, dict) or not {"value", "u"} <= entry.keys():
        raise ComparisonInputError(
            f"{path}: no {key!r} entry with value and u (a budget without a reference area has "
            "no ratio; choose another --quantity)"
        )
    if quantity == "intensity" and entry.get("t_ref_k", 296.0) != 296.0:
        raise ComparisonInputError(
            f"{path}: intensity is at T_ref = {entry['t_ref_k']} K; compare S at 296 K"
        )
    factor = _factor(quantity, entry.get("unit", unit_of(quantity)), f"{path}: field {key}.unit")
    value, u = _finite(entry["value"], entry["u"], f"{path}: field {key}")
    dof = entry.get("effective_dof", "inf")  # GUM nu_eff of that budget ("inf" when infinite)
    dof = math.inf if dof in ("inf", None) else float(dof)
    return LabResult(lab, value * factor, u * factor, str(path), dof, unit_of(quantity))


def _factor(quantity: str, unit: str, where: str) -> float:
    unit_name, accepted, _, _ = _spec(quantity)
    if quantity == "other":
        if not unit:
            raise ComparisonInputError(f"{where}: state the unit of the value and u")
        return 1.0
    if unit not in accepted:
        raise ComparisonInputError(
            f"{where}: unit {unit!r} is not a unit of {quantity}; use one of "
            f"{', '.join(repr(a) for a in accepted)} ({unit_name} is used throughout), or "
            "--quantity other to compare another measurand in the unit its rows state"
        )
    return accepted[unit]


def _finite(value, u, where: str) -> tuple[float, float]:
    try:
        value, u = float(value), float(u)
    except (TypeError, ValueError):
        raise ComparisonInputError(f"{where}: value and u must be numbers") from None
    if not (math.isfinite(value) and math.isfinite(u) and u > 0):
        raise ComparisonInputError(f"{where}: value must be finite and u finite and > 0")
    return value, u


def read_results_csv(path, quantity: str) -> list:
    """Results from elsewhere: columns lab, value, unit and either u, or U with k; optional dof.

    ``u`` is the standard uncertainty; a laboratory that reports an expanded uncertainty gives
    ``U`` and its coverage factor ``k`` (u = U/k). Lines starting with # are comments.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ComparisonInputError(f"{path}: cannot read ({exc.strerror})") from None
    rows = [(n, line) for n, line in enumerate(text.splitlines(), 1) if _is_data(line)]
    if not rows:
        raise ComparisonInputError(f"{path}: no header line (lab,value,u,unit)")
    header = [h.strip() for h in next(csv.reader([rows[0][1]]))]
    _check_header(path, rows[0][0], header)
    results = []
    for n, line in rows[1:]:
        cells = [c.strip() for c in next(csv.reader([line]))]
        if len(cells) != len(header):
            raise ComparisonInputError(
                f"{path}, line {n}: {len(cells)} columns where the header has {len(header)}"
            )
        results.append(_csv_row(path, n, dict(zip(header, cells)), quantity))
    return results


def _is_data(line: str) -> bool:
    return bool(line.strip()) and not line.lstrip().startswith("#")


def _check_header(path, n: int, header: list) -> None:
    missing = [c for c in ("lab", "value", "unit") if c not in header]
    if not ("u" in header or {"U", "k"} <= set(header)):
        missing.append("u (or U and k)")
    if missing:
        raise ComparisonInputError(
            f"{path}, line {n}: missing column(s) {', '.join(missing)}; the header must be "
            "lab,value,u,unit[,dof] (or U,k in place of u)"
        )


def _csv_row(path, n: int, row: dict, quantity: str) -> LabResult:
    """One CSV row as a LabResult in the comparison unit."""
    where = f"{path}, line {n}"
    if not row["lab"]:
        raise ComparisonInputError(f"{where}, column lab: empty laboratory name")
    value = _cell(row, "value", where)
    if "u" in row and row["u"]:
        u = _cell(row, "u", where)
    else:
        u = _cell(row, "U", where) / _cell(row, "k", where)
    dof = _cell(row, "dof", where) if row.get("dof") else math.inf
    if not (u > 0 and dof > 0):
        raise ComparisonInputError(f"{where}: u (or U, k) and dof must be > 0")
    factor = _factor(quantity, row["unit"], f"{where}, column unit")
    unit = row["unit"] if quantity == "other" else unit_of(quantity)
    return LabResult(row["lab"], value * factor, u * factor, f"{path}:{n}", dof, unit)


def _cell(row: dict, column: str, where: str) -> float:
    try:
        v = float(row.get(column, ""))
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise ComparisonInputError(
            f"{where}, column {column}: expected a finite number, got {row.get(column)!r}"
        )
    return v


def read_correlations(path, labs) -> np.ndarray:
    """The correlation matrix of the results from a CSV of pairs: lab_a,lab_b,r.

    Results that share an input (the same H, the same manometer) are correlated; a pair not
    listed is independent. Returns (n, n) in the order of ``labs``.
    """
    path = Path(path)
    labs = list(labs)
    r = np.eye(len(labs))
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ComparisonInputError(f"{path}: cannot read ({exc.strerror})") from None
    rows = [(n, line) for n, line in enumerate(text.splitlines(), 1) if _is_data(line)]
    header = [h.strip() for h in next(csv.reader([rows[0][1]]))] if rows else []
    if header != ["lab_a", "lab_b", "r"]:
        raise ComparisonInputError(f"{path}, line 1: the header must be lab_a,lab_b,r")
    for n, line in rows[1:]:
        i, j, rho = _pair(path, n, line, labs)
        r[i, j] = r[j, i] = rho
    return r


def _pair(path, n: int, line: str, labs: list) -> tuple[int, int, float]:
    cells = [c.strip() for c in next(csv.reader([line]))]
    where = f"{path}, line {n}"
    if len(cells) != 3:
        raise ComparisonInputError(f"{where}: expected lab_a,lab_b,r")
    for column, name in zip(("lab_a", "lab_b"), cells):
        if name not in labs:
            raise ComparisonInputError(
                f"{where}, column {column}: {name!r} is not a result of this comparison "
                f"({', '.join(labs)})"
            )
    if cells[0] == cells[1]:
        raise ComparisonInputError(f"{where}: a result is not correlated with itself here")
    rho = _cell({"r": cells[2]}, "r", where)
    if not -1.0 < rho < 1.0:
        raise ComparisonInputError(f"{where}, column r: {rho} is outside (-1, 1)")
    return labs.index(cells[0]), labs.index(cells[1]), rho


def si_factor(quantity: str):
    """(SI unit, factor from the comparison unit to it), or (None, None) for a ratio."""
    spec = _spec(quantity)
    return spec[2], spec[3]
