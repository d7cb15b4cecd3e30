"""A lab's own files -> a measurement bundle: the ``bayes-tfcrds import`` edge.

A lab folder holds what a CRDS lab keeps: ring-down records (one 2-D array with one row per
cavity mode, or one file per mode), a beat-note table, a CMDS table, and a short ``lab.toml``
that says which file and column holds what, in which unit, and the sample conditions.
Everything is converted to SI here (:mod:`bayes_tfcrds.bundle.units`), so the bundle and every
analysis after it see Hz, s, V, Pa, K only. Labs that keep only a spectrum, tau(nu) or
alpha(nu) with uncertainties, describe it in a ``[spectrum]`` table
(:func:`read_lab_spectrum`).

Files: CSV/TSV/whitespace text (``#`` starts a comment line; tables have one header line),
NPY (2-D signal arrays) and NPZ (arrays by key; for tables each key is a column). Every error
names the file, and for text files the line and column, and says what to do.

The README ("Bringing your own data") shows a complete ``lab.toml``;
``bayes-tfcrds import --example DIR`` writes a worked example folder.
"""

from __future__ import annotations

import difflib
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bayes_tfcrds.bundle.records import Bundle, BundleError, Sample
from bayes_tfcrds.bundle.units import UnitError, from_si, to_si
from bayes_tfcrds.core.constants import C

LAB_TOML = "lab.toml"


class LabFolderError(ValueError):
    """A lab folder that cannot be imported; the message names file, line, column and the fix."""


# --------------------------------------------------------------------------- tables


@dataclass(frozen=True)
class Table:
    """A table read from one file: column name -> float64 values, and where each row came from.

    ``lines`` (n,) are the 1-based text lines of the rows (0 for binary files).
    """

    path: Path
    columns: dict
    lines: np.ndarray
    header_line: int = 0

    @property
    def n_rows(self) -> int:
        return self.lines.size


def _delimiter(path: Path, line: str, given: str | None) -> str | None:
    """The field separator: given, tab for .tsv, else the first of , tab ; in the line."""
    if given is not None:
        return given
    if path.suffix.lower() in (".tsv", ".tab"):
        return "\t"
    for d in (",", "\t", ";"):
        if d in line:
            return d
    return None  # whitespace


def _split(line: str, delim: str | None) -> list[str]:
    return [f.strip() for f in (line.split() if delim is None else line.split(delim))]


def _text_rows(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of the non-blank, non-comment lines of a text file."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise LabFolderError(f"{path}: file not found; check the file name in {LAB_TOML}") from None
    except UnicodeDecodeError as exc:
        raise LabFolderError(
            f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); export it as UTF-8 "
            "CSV/TSV, or as .npy/.npz"
        ) from None
    rows = [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines())]
    return [(i, ln) for i, ln in rows if ln and not ln.startswith("#")]


def _number(text: str, path: Path, line: int, col: int, name: str | None) -> float:
    try:
        return float(text)
    except ValueError:
        what = f" ({name!r})" if name else ""
        raise LabFolderError(
            f"{path}:{line}:{col}: {text!r} in column {col}{what} is not a number; fix the "
            "value (decimal point '.', no units in cells; the unit goes in lab.toml)"
        ) from None


def _parse_rows(path: Path, rows, delim, names=None) -> np.ndarray:
    width = len(names) if names is not None else len(_split(rows[0][1], delim))
    out = np.empty((len(rows), width))
    for r, (line, text) in enumerate(rows):
        fields = _split(text, delim)
        if len(fields) != width:
            raise LabFolderError(
                f"{path}:{line}: {len(fields)} fields where "
                + ("the header has" if names is not None else "the first row has")
                + f" {width}; every row needs one value per column"
            )
        for c, field in enumerate(fields):
            out[r, c] = _number(field, path, line, c + 1, None if names is None else names[c])
    return out


def read_table(path, delimiter: str | None = None) -> Table:
    """A table from CSV/TSV text (one header line of column names) or from an NPZ (keys)."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        arrays = _npz(path)
        columns = {k: np.asarray(v, float).reshape(-1) for k, v in arrays.items()}
        sizes = {k: v.size for k, v in columns.items()}
        if len(set(sizes.values())) > 1:
            raise LabFolderError(
                f"{path}: its arrays differ in length {sizes}; a table's "
                "columns must have equal lengths"
            )
        n = next(iter(sizes.values()), 0)
        return Table(path, columns, np.zeros(n, dtype=int))
    rows = _text_rows(path)
    if len(rows) < 2:
        raise LabFolderError(
            f"{path}: needs a header line with the column names and at least one row of data"
        )
    delim = _delimiter(path, rows[0][1], delimiter)
    names = _split(rows[0][1], delim)
    values = _parse_rows(path, rows[1:], delim, names)
    columns = {name: values[:, i] for i, name in enumerate(names)}
    return Table(path, columns, np.array([ln for ln, _ in rows[1:]]), rows[0][0])


def _npz(path: Path) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise LabFolderError(f"{path}: file not found; check the file name in {LAB_TOML}") from None
    except (ValueError, OSError) as exc:
        raise LabFolderError(f"{path}: cannot be read as NPZ ({exc})") from None


def read_matrix(path, key: str | None = None, delimiter: str | None = None) -> np.ndarray:
    """A 2-D float64 array from text (no header: one row per line), .npy, or .npz (``key``)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        arrays = _npz(path)
        if key is None and len(arrays) == 1:
            key = next(iter(arrays))
        if key not in arrays:
            raise LabFolderError(
                f"{path}: no array {key!r}; it holds {sorted(arrays)}: name one with signal_key"
            )
        a = arrays[key]
    elif suffix == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except FileNotFoundError:
            raise LabFolderError(
                f"{path}: file not found; check the file name in {LAB_TOML}"
            ) from None
        except (ValueError, OSError) as exc:
            raise LabFolderError(f"{path}: cannot be read as NPY ({exc})") from None
    else:
        rows = _text_rows(path)
        if not rows:
            raise LabFolderError(f"{path}: holds no data rows")
        a = _parse_rows(path, rows, _delimiter(path, rows[0][1], delimiter))
    a = np.asarray(a)
    if a.dtype.kind not in "iuf" or a.ndim != 2:
        raise LabFolderError(
            f"{path}: expected a 2-D array of numbers (one row per cavity mode), found "
            f"dtype {a.dtype}, shape {a.shape}"
        )
    return a.astype(np.float64)


# --------------------------------------------------------------------------- lab.toml


def _close(name: str, known) -> str:
    hit = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return f" (did you mean {hit[0]!r}?)" if hit else ""


def _check_keys(table: dict, known, where: str) -> None:
    for key in table:
        if key not in known:
            raise LabFolderError(
                f"{LAB_TOML} [{where}]: unknown key {key!r}{_close(key, known)}; known keys: "
                f"{', '.join(known)}"
            )


def _quantity(table: dict, key: str, kind: str, where: str, required=True, difference=False):
    """A number (SI), a string "value unit" or {value, unit} from lab.toml, in SI."""
    if key not in table:
        if required:
            raise LabFolderError(
                f'{LAB_TOML} [{where}]: {key!r} is missing; add e.g. {key} = "VALUE UNIT"'
            )
        return None
    raw = table[key]
    if isinstance(raw, dict):
        value, unit = raw.get("value"), raw.get("unit")
    elif isinstance(raw, str):
        parts = raw.split(None, 1)
        value, unit = parts[0] if parts else "", parts[1].strip() if len(parts) > 1 else None
    else:
        value, unit = raw, None
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise LabFolderError(
            f"{LAB_TOML} [{where}] {key} = {raw!r}: expected a number with an optional unit, "
            'e.g. "5.0 Torr" (a bare number is SI)'
        ) from None
    if not np.isfinite(number):
        raise LabFolderError(f"{LAB_TOML} [{where}] {key} = {raw!r}: must be finite")
    try:
        return float(to_si(number, unit, kind, difference))
    except UnitError as exc:
        raise LabFolderError(f"{LAB_TOML} [{where}] {key}: {exc}") from None


#: lab.toml field -> (bundle field, unit kind, required, is a difference)
SAMPLE_FIELDS = {
    "nu0": ("nu0_hz", "frequency", True, False),
    "pressure": ("pressure_pa", "pressure", True, False),
    "pressure_u": ("pressure_u_pa", "pressure", True, True),
    "temperature": ("temperature_k", "temperature", True, False),
    "temperature_u": ("temperature_u_k", "temperature", True, True),
    "mole_fraction": ("mole_fraction", "fraction", False, False),
    "mass": ("mass_u", "mass", False, False),
}
#: table columns per section: field -> (unit kind, required, is a difference)
COLUMNS = {
    "ringdowns": {
        "nu": ("frequency", True, False),
        "n_avg": ("count", False, False),
        "noise": ("voltage", False, True),
        "signal": ("voltage", True, False),
        "time": ("time", False, False),
    },
    "beat_note": {
        "f": ("frequency", True, False),
        "b12": ("voltage", True, False),
        "b12_u": ("voltage", False, True),
        "i1": ("voltage", False, False),
        "i2": ("voltage", False, False),
    },
    "cmds": {
        "nu": ("frequency", True, False),
        "shift": ("frequency", True, True),
        "shift_u": ("frequency", True, True),
        "width": ("frequency", False, True),
        "width_u": ("frequency", False, True),
    },
    "spectrum": {
        "nu": ("frequency", True, False),
        "tau": ("time", False, False),
        "tau_u": ("time", False, True),
        "alpha": ("absorption", False, False),
        "alpha_u": ("absorption", False, True),
    },
}


def _section(doc: dict, key: str, where: str) -> dict:
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise LabFolderError(f"{LAB_TOML} [{where}]: expected a table")
    return value


def _columns(table: Table, spec: dict, kind: str, where: str, fields=None) -> dict:
    """Mapped columns of ``table`` in SI: field -> array (absent optional fields omitted)."""
    names = spec.get("columns", {})
    units = spec.get("units", {})
    if not (isinstance(names, dict) and isinstance(units, dict)):
        raise LabFolderError(
            f'{LAB_TOML} [{where}]: columns and units are tables, e.g. columns = {{ nu = "nu_GHz" '
            '}, units = { nu = "GHz" }'
        )
    known = COLUMNS[kind]
    for key in (*names, *units):
        if key not in known:
            raise LabFolderError(
                f"{LAB_TOML} [{where}]: no field {key!r} in columns/units{_close(key, known)}; "
                f"fields: {', '.join(known)}"
            )
    out = {}
    for field, (unit_kind, required, difference) in known.items():
        if fields is not None and field not in fields:
            continue
        column = names.get(field, field)
        if column not in table.columns:
            if required or field in names:
                raise LabFolderError(
                    f"{table.path}:{table.header_line or 1}"
                    f": no column {column!r} for {field} (columns: {', '.join(table.columns)}); "
                    f'name it in {LAB_TOML} [{where}] columns = {{ {field} = "..." }}'
                )
            continue
        values = table.columns[column]
        try:
            out[field] = to_si(values, units.get(field), unit_kind, difference)
        except UnitError as exc:
            raise LabFolderError(f"{LAB_TOML} [{where}] units.{field}: {exc}") from None
    return out


def _whole(values, table: Table, column: str) -> np.ndarray:
    bad = np.flatnonzero(values != np.round(values))
    if bad.size:
        i = int(bad[0])
        raise LabFolderError(
            f"{table.path}:{table.lines[i]}: {column} = {values[i]!r} is not a whole number of "
            "averaged acquisitions"
        )
    return values.astype(np.int64)


def _sample(doc: dict) -> Sample:
    s = _section(doc, "sample", "sample")
    _check_keys(s, ("molecule", "line", *SAMPLE_FIELDS), "sample")
    for key in ("molecule", "line"):
        if not isinstance(s.get(key), str):
            raise LabFolderError(
                f"{LAB_TOML} [sample]: {key!r} (text) is missing, e.g. "
                + ('molecule = "CO"' if key == "molecule" else 'line = "(3-0) R(23)"')
            )
    values = {
        name: _quantity(s, key, kind, "sample", required, diff)
        for key, (name, kind, required, diff) in SAMPLE_FIELDS.items()
    }
    if values["mole_fraction"] is None:
        values["mole_fraction"] = 1.0
    return Sample(molecule=s["molecule"], line=s["line"], **values)


def _cavity(doc: dict) -> dict:
    c = _section(doc, "cavity", "cavity")
    _check_keys(c, ("fsr", "length", "finesse"), "cavity")
    fsr = _quantity(c, "fsr", "frequency", "cavity", required=False)
    if fsr is None:
        length = _quantity(c, "length", "length", "cavity", required=False)
        if length is None:
            raise LabFolderError(
                f'{LAB_TOML} [cavity]: give the free spectral range (fsr = "250 MHz") or the '
                'mirror spacing (length = "60 cm"; fsr = c/(2 length))'
            )
        fsr = C / (2.0 * length)
    return {"fsr_hz": fsr, "finesse": _quantity(c, "finesse", "count", "cavity", required=False)}


def _file(folder: Path, spec: dict, key: str, where: str) -> Path:
    if not isinstance(spec.get(key), str):
        raise LabFolderError(
            f"{LAB_TOML} [{where}]: {key!r} (a file name in the folder) is missing"
        )
    return folder / spec[key]


_RD_KEYS = (
    "modes",
    "signal",
    "records",
    "signal_key",
    "transpose",
    "dt",
    "t0",
    "delimiter",
    "columns",
    "units",
)


def _ringdowns(folder: Path, spec: dict, where: str) -> dict:
    _check_keys(spec, _RD_KEYS, where)
    delim = spec.get("delimiter")
    modes = read_table(_file(folder, spec, "modes", where), delim)
    cols = _columns(modes, spec, "ringdowns", where, fields=("nu", "n_avg", "noise"))
    out = {"nu_hz": cols["nu"]}
    if "n_avg" in cols:
        out["n_avg"] = _whole(cols["n_avg"], modes, spec.get("columns", {}).get("n_avg", "n_avg"))
    if "noise" in cols:
        out["noise_v"] = cols["noise"]
    dt = _quantity(spec, "dt", "time", where, required=False, difference=True)
    t0 = _quantity(spec, "t0", "time", where, required=False)
    if "signal" in spec:
        signal = read_matrix(_file(folder, spec, "signal", where), spec.get("signal_key"), delim)
        if spec.get("transpose", False):
            signal = signal.T
        if signal.shape[0] != modes.n_rows:
            raise LabFolderError(
                f"{folder / spec['signal']}: {signal.shape[0]} rows (records), but {modes.path} "
                f"lists {modes.n_rows} cavity modes; one row per mode in the order of the modes "
                "table (transpose = true if your records are columns)"
            )
        out["signal_v"] = _signal_si(signal, spec, where)
    else:
        out["signal_v"], dt, t0 = _per_mode_records(folder, spec, modes, where, dt, t0)
    if dt is None or t0 is None:
        raise LabFolderError(
            f"{LAB_TOML} [{where}]: give the sample interval and the time of the first sample "
            'from laser extinction, e.g. dt = "20 ns" and t0 = "-2 us" (or a time column in '
            "each record file)"
        )
    out.update(dt_s=dt, t0_s=t0)
    return out


def _signal_si(signal: np.ndarray, spec: dict, where: str) -> np.ndarray:
    """Record values in volts, from the unit ``units.signal`` (V when absent)."""
    try:
        return to_si(signal, spec.get("units", {}).get("signal"), "voltage")
    except UnitError as exc:
        raise LabFolderError(f"{LAB_TOML} [{where}] units.signal: {exc}") from None


def _natural(path: Path):
    """Sort key that puts mode_2 before mode_10."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def _per_mode_records(folder: Path, spec: dict, modes: Table, where: str, dt, t0):
    """One record file per cavity mode (``records`` glob, natural name order = modes order).

    Each file is a 1-D .npy or a table with a ``signal`` column and, optionally, a ``time``
    column from which dt and t0 are read (uniform sampling checked). Returns (signal, dt, t0).
    """
    pattern = spec.get("records")
    if not isinstance(pattern, str):
        raise LabFolderError(
            f'{LAB_TOML} [{where}]: give signal = "FILE" (one 2-D array, one row per cavity '
            'mode) or records = "DIR/mode_*.csv" (one file per mode, in the modes table\'s order)'
        )
    paths = sorted(folder.glob(pattern), key=_natural)
    if len(paths) != modes.n_rows:
        raise LabFolderError(
            f"{LAB_TOML} [{where}] records = {pattern!r}: {len(paths)} files match, but "
            f"{modes.path} lists {modes.n_rows} cavity modes; one file per mode"
        )
    rows, time = [], None
    for path in paths:
        if path.suffix.lower() == ".npy":
            rows.append(_signal_si(read_matrix_row(path), spec, where))
            continue
        table = read_table(path, spec.get("delimiter"))
        cols = _columns(table, spec, "ringdowns", where, fields=("signal", "time"))
        rows.append(cols["signal"])
        if "time" in cols:
            t = cols["time"]
            if time is None:
                time = t
            elif t.shape != time.shape or not np.allclose(
                t, time, rtol=0, atol=1e-6 * abs(t[1] - t[0])
            ):
                raise LabFolderError(
                    f"{path}: its time column differs from that of {paths[0]}; all records of a "
                    "configuration share one time axis"
                )
        if rows[-1].shape != rows[0].shape:
            raise LabFolderError(
                f"{path}: {rows[-1].size} samples, {paths[0]} has {rows[0].size}; all records "
                "of a configuration need the same number of samples"
            )
    if time is not None:
        step = np.diff(time)
        if time.size < 2 or np.ptp(step) > 1e-6 * abs(step[0]):  # jitter of printed digits
            raise LabFolderError(
                f"{paths[0]}: the time column is not uniformly sampled (steps "
                f"{step.min():.6g} to {step.max():.6g} s); resample, or give dt and t0"
            )
        dt = float((time[-1] - time[0]) / (time.size - 1)) if dt is None else dt
        t0 = float(time[0]) if t0 is None else t0
    return np.vstack(rows), dt, t0


def read_matrix_row(path: Path) -> np.ndarray:
    """A 1-D record from a .npy file (float64)."""
    try:
        a = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise LabFolderError(f"{path}: cannot be read as NPY ({exc})") from None
    if a.dtype.kind not in "iuf" or a.ndim != 1:
        raise LabFolderError(f"{path}: expected a 1-D array of numbers, found shape {a.shape}")
    return a.astype(np.float64)


def _beat_note(folder: Path, spec: dict, where: str) -> dict:
    _check_keys(spec, ("file", "delimiter", "columns", "units", "i1", "i2"), where)
    table = read_table(_file(folder, spec, "file", where), spec.get("delimiter"))
    cols = _columns(table, spec, "beat_note", where)
    out = {"f_hz": cols["f"], "b12_v": cols["b12"]}
    if "b12_u" in cols:
        out["b12_u_v"] = cols["b12_u"]
    for key in ("i1", "i2"):
        if key in spec:
            out[f"{key}_v"] = _quantity(spec, key, "voltage", where)
        elif key in cols:
            out[f"{key}_v"] = cols[key]
        else:
            raise LabFolderError(
                f'{table.path}: no {key} column, and no {key} = "VALUE mV" in {LAB_TOML} '
                f"[{where}]: the single-beam DC level is needed to normalise |H|"
            )
    return out


def _cmds(folder: Path, spec: dict, where: str) -> dict:
    _check_keys(spec, ("file", "delimiter", "columns", "units"), where)
    table = read_table(_file(folder, spec, "file", where), spec.get("delimiter"))
    cols = _columns(table, spec, "cmds", where)
    return {f"{k}_hz": v for k, v in cols.items()}


def _read_doc(folder) -> tuple[Path, dict]:
    folder = Path(folder)
    toml = folder if folder.is_file() else folder / LAB_TOML
    if not toml.is_file():
        raise LabFolderError(
            f"{toml}: not found; a lab folder needs a {LAB_TOML} (bayes-tfcrds import --example "
            "DIR writes a worked example)"
        )
    try:
        doc = tomllib.loads(toml.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise LabFolderError(f"{toml}: not valid TOML: {exc}") from None
    return toml.parent, doc


def read_lab_folder(folder) -> Bundle:
    """The bundle (SI) a lab folder describes; LabFolderError names file, line, column and fix."""
    folder, doc = _read_doc(folder)
    _check_keys(doc, ("description", "sample", "cavity", "configs", "spectrum"), "top level")
    configs = _section(doc, "configs", "configs")
    if not configs:
        raise LabFolderError(
            f"{LAB_TOML}: no [configs.NAME] table; describe at least one detection "
            "configuration (its ringdowns; beat_note and cmds optional)"
            + (
                " (a folder with only [spectrum] is for linefit --spectrum)"
                if "spectrum" in doc
                else ""
            )
        )
    arrays = {}
    for name, spec in configs.items():
        where = f"configs.{name}"
        if not isinstance(spec, dict):
            raise LabFolderError(f"{LAB_TOML} [{where}]: expected a table")
        _check_keys(spec, ("description", "ringdowns", "beat_note", "cmds"), where)
        cfg = {
            "ringdowns": _ringdowns(
                folder, _section(spec, "ringdowns", where), where + ".ringdowns"
            )
        }
        if "beat_note" in spec:
            cfg["transfer_function"] = _beat_note(folder, spec["beat_note"], where + ".beat_note")
        if "cmds" in spec:
            cfg["cmds"] = _cmds(folder, spec["cmds"], where + ".cmds")
        if "description" in spec:
            cfg["description"] = str(spec["description"])
        arrays[name] = cfg
    return Bundle.from_arrays(
        _sample(doc), _cavity(doc), arrays, description=doc.get("description")
    )


def import_lab_folder(folder, output) -> Bundle:
    """Read a lab folder and write its bundle to ``output`` (checked against FORMAT.md)."""
    from bayes_tfcrds.bundle.writer import save_bundle

    bundle = read_lab_folder(folder)
    try:
        save_bundle(bundle, output)
    except BundleError as exc:
        raise LabFolderError(
            f"{Path(folder) / LAB_TOML}: the imported data break the bundle contract (paths are "
            "the bundle's: /sample = [sample], /configs/NAME/ringdowns = [configs.NAME.ringdowns] "
            "and its files, transfer_function = beat_note): " + exc.one_line(shown=5)
        ) from None
    return bundle


# --------------------------------------------------------------------------- spectrum level


@dataclass(frozen=True)
class LabSpectrum:
    """A spectrum kept by a lab: decay times tau(nu) (s) or absorption alpha(nu) (1/m).

    ``quantity`` is ``tau`` or ``alpha``; ``values`` and ``u`` (standard uncertainties) are SI,
    ``nu_hz`` absolute optical frequencies (Hz). No ring-down records and no beat note: a line
    fit of it has no transfer-function rows.
    """

    sample: Sample
    nu_hz: np.ndarray
    quantity: str
    values: np.ndarray
    u: np.ndarray
    source: str


def read_lab_spectrum(folder) -> LabSpectrum:
    """The ``[spectrum]`` table of a lab folder's lab.toml with its [sample], in SI."""
    folder, doc = _read_doc(folder)
    spec = _section(doc, "spectrum", "spectrum")
    if not spec:
        raise LabFolderError(
            f'{folder / LAB_TOML}: no [spectrum] table; add one with file = "FILE.csv" and '
            "columns nu and tau, tau_u (or alpha, alpha_u)"
        )
    _check_keys(spec, ("file", "delimiter", "columns", "units"), "spectrum")
    table = read_table(_file(folder, spec, "file", "spectrum"), spec.get("delimiter"))
    cols = _columns(table, spec, "spectrum", "spectrum")
    for q in ("tau", "alpha"):
        if q in cols and f"{q}_u" in cols:
            return LabSpectrum(
                _sample(doc), cols["nu"], q, cols[q], cols[f"{q}_u"], str(table.path)
            )
    raise LabFolderError(
        f"{table.path}: needs columns tau and tau_u (decay time and its standard uncertainty) or "
        f"alpha and alpha_u (columns: {', '.join(table.columns)}); map them in {LAB_TOML} "
        "[spectrum] columns"
    )


# --------------------------------------------------------------------------- writing


#: units the worked example writes in (what labs typically keep)
EXAMPLE_UNITS = {
    "signal": "mV",
    "noise": "mV",
    "nu": "GHz",
    "f": "MHz",
    "b12": "mV",
    "b12_u": "mV",
    "i1": "mV",
    "i2": "mV",
    "shift": "kHz",
    "shift_u": "kHz",
    "width": "kHz",
    "width_u": "kHz",
}
_KIND = {
    "signal": "voltage",
    "noise": "voltage",
    "nu": "frequency",
    "f": "frequency",
    "b12": "voltage",
    "b12_u": "voltage",
    "i1": "voltage",
    "i2": "voltage",
    "shift": "frequency",
    "shift_u": "frequency",
    "width": "frequency",
    "width_u": "frequency",
}


def _fmt(x) -> str:
    return repr(float(x))  # the shortest text that reads back as the same float64


def _write_table(path: Path, columns: dict, units: dict) -> None:
    """CSV with a header; each value in its lab unit, digits enough to read back exactly."""
    names = list(columns)
    header = ",".join(f"{n}_{units[n]}" if n in units else n for n in names)
    data = [
        np.asarray(
            from_si(
                np.asarray(columns[n], float),
                units.get(n),
                _KIND.get(n, "count"),
                n.endswith("_u") or n == "noise",
            )
        )
        if n in units
        else np.asarray(columns[n], float)
        for n in names
    ]
    lines = [header] + [",".join(_fmt(c[i]) for c in data) for i in range(len(data[0]))]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _toml_str(text: str) -> str:
    return '"' + str(text).replace("\\", "\\\\").replace('"', '\\"') + '"'


def _toml_cols(names, units: dict) -> list[str]:
    cols = ", ".join(f'{n} = "{n}_{units[n]}"' if n in units else f'{n} = "{n}"' for n in names)
    us = ", ".join(f'{n} = "{units[n]}"' for n in names if n in units)
    return [f"columns = {{ {cols} }}", f"units = {{ {us} }}"]


def write_lab_folder(bundle: Bundle, folder) -> list[Path]:
    """Write ``bundle`` as a lab folder (CSV in lab units + lab.toml); returns the files written.

    Numbers are written as the shortest decimal that reads back as the same float64 in the
    lab unit, so an import gives back the bundle's arrays to within the two unit conversions
    (a relative 2.2e-16 each).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    s, u = bundle.sample, EXAMPLE_UNITS
    lines = [
        "# A lab folder: what a CRDS lab keeps, described for `bayes-tfcrds import`.",
        '# Quantities are "VALUE UNIT" (a bare number is SI); columns map field -> header.',
    ]
    if bundle.description is not None:
        lines.append(f"description = {_toml_str(bundle.description)}")
    lines += [
        "",
        "[sample]",
        f"molecule = {_toml_str(s.molecule)}",
        f"line = {_toml_str(s.line)}",
        f'nu0 = "{_fmt(from_si(s.nu0_hz, "cm^-1", "frequency"))} cm^-1"',
        f'pressure = "{_fmt(from_si(s.pressure_pa, "Torr", "pressure"))} Torr"',
        f'pressure_u = "{_fmt(from_si(s.pressure_u_pa, "Torr", "pressure", True))} Torr"',
        f'temperature = "{_fmt(from_si(s.temperature_k, "degC", "temperature"))} degC"',
        f'temperature_u = "{_fmt(s.temperature_u_k)} K"',
        f"mole_fraction = {_fmt(s.mole_fraction)}",
    ]
    if s.mass_u is not None:
        lines.append(f'mass = "{_fmt(s.mass_u)} u"')
    lines += [
        "",
        "[cavity]",
        f'fsr = "{_fmt(from_si(bundle.cavity.fsr_hz, "MHz", "frequency"))} MHz"',
    ]
    if bundle.cavity.finesse is not None:
        lines.append(f"finesse = {_fmt(bundle.cavity.finesse)}")
    written = []
    for name, cfg in bundle.configs.items():
        rd = cfg.ringdowns
        lines += ["", f"[configs.{name}]"]
        if cfg.description is not None:
            lines.append(f"description = {_toml_str(cfg.description)}")
        modes = {"nu": rd.nu_hz}
        if rd.n_avg is not None:
            modes["n_avg"] = rd.n_avg
        if rd.noise_v is not None and rd.noise_v.ndim == 1:
            modes["noise"] = rd.noise_v
        _write_table(folder / f"{name}_modes.csv", modes, u)
        sig = folder / f"{name}_ringdowns.csv"
        body = from_si(rd.signal_v, "mV", "voltage")
        sig.write_text(
            "# one row per cavity mode (the rows of the modes table), one column per sample, mV\n"
            + "\n".join(",".join(map(_fmt, row)) for row in body)
            + "\n",
            encoding="utf-8",
        )
        lines += [
            "",
            f"[configs.{name}.ringdowns]",
            f'modes = "{name}_modes.csv"',
            f'signal = "{sig.name}"',
            f'dt = "{_fmt(from_si(rd.dt_s, "ns", "time"))} ns"',
            f't0 = "{_fmt(from_si(rd.t0_s, "us", "time"))} us"',
            *_toml_cols([*modes, "signal"], u),
        ]
        written += [folder / f"{name}_modes.csv", sig]
        tf = cfg.transfer_function
        if tf is not None:
            cols = {"f": tf.f_hz, "b12": tf.b12_v}
            if tf.b12_u_v is not None:
                cols["b12_u"] = tf.b12_u_v
            scalars = []
            for key in ("i1", "i2"):
                level = getattr(tf, f"{key}_v")
                if np.ndim(level):
                    cols[key] = level
                else:
                    scalars.append(f'{key} = "{_fmt(from_si(level, "mV", "voltage"))} mV"')
            _write_table(folder / f"{name}_beat.csv", cols, u)
            lines += [
                "",
                f"[configs.{name}.beat_note]",
                f'file = "{name}_beat.csv"',
                *scalars,
                *_toml_cols(cols, u),
            ]
            written.append(folder / f"{name}_beat.csv")
        if cfg.cmds is not None:
            cm = cfg.cmds
            cols = {"nu": cm.nu_hz, "shift": cm.shift_hz, "shift_u": cm.shift_u_hz}
            if cm.width_hz is not None:
                cols["width"] = cm.width_hz
                if cm.width_u_hz is not None:
                    cols["width_u"] = cm.width_u_hz
            _write_table(folder / f"{name}_cmds.csv", cols, u)
            lines += [
                "",
                f"[configs.{name}.cmds]",
                f'file = "{name}_cmds.csv"',
                *_toml_cols(cols, u),
            ]
            written.append(folder / f"{name}_cmds.csv")
    (folder / LAB_TOML).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return [folder / LAB_TOML, *written]


def lab_folder_exists(folder) -> bool:
    """Whether ``folder`` already holds a lab.toml (the example writer will not replace one)."""
    return os.path.exists(Path(folder) / LAB_TOML)
