"""Scoring another simulator's results against a reference case (``refsim compare``).

Their results are a CSV file with a header line holding the columns ``quantity``, ``x`` and ``value`` (other
columns are ignored, so a package's own ``reference.csv`` reads back), one row per sample, in the reference's
units (SI)::

    quantity,x,value
    indentation_force,0.00020,0.512        # a curve: x in the quantity's x unit, any points, any order
    indentation_force,0.00025,0.655
    puncture_force,,0.8                    # a scalar: x empty

Every quantity of the case must be there. A curve is interpolated linearly onto the reference's sampling
points, which must lie within the x range they give. A refsim results file (.h5) is read directly instead.

Per sampling point: the difference d = theirs − reference, the error in units of the reference's uncertainty
e = |d| / U (infinite for U = 0 and d ≠ 0), and the verdict: pass when |d| ≤ U + T, T the case's modelling
tolerance (the quantity's ``tolerance`` times its scale: the largest |reference| of the quantity). A quantity
passes when every sample does.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from refsim.reference.build import read_case_reference
from refsim.reference.cases import case_values, load_case, sample_curve

__all__ = [
    "REQUIRED_COLUMNS",
    "Comparison",
    "compare",
    "comparison_figure",
    "format_comparison",
    "read_their_csv",
    "write_their_csv",
]

REQUIRED_COLUMNS = ("quantity", "x", "value")


@dataclass(frozen=True)
class Comparison:
    """One quantity of a case compared with their results.

    Attributes
    ----------
    quantity, kind, unit, x_unit : As in the case.
    at : Sampling points, shape (k,) (empty for a scalar).
    reference, uncertainty, band : Reference value, its uncertainty U and the band U + T, shape (k,).
    theirs : Their values at the sampling points, shape (k,).
    error : |theirs − reference| / U, shape (k,).
    passed : Per sample, |theirs − reference| ≤ U + T, shape (k,).
    """

    quantity: str
    kind: str
    unit: str
    x_unit: str
    at: np.ndarray
    reference: np.ndarray
    uncertainty: np.ndarray
    band: np.ndarray
    theirs: np.ndarray
    error: np.ndarray
    passed: np.ndarray

    @property
    def all_passed(self) -> bool:
        """True when every sample is inside the band."""
        return bool(np.all(self.passed))


def read_their_csv(path, case) -> dict[str, np.ndarray]:
    """Their values of every quantity of ``case``, at the reference's sampling points.

    Raises
    ------
    ValueError
        Naming the file, line, column and what is expected: missing columns, a value that is not a number, an
        unknown or missing quantity, a curve that does not cover the sampling points.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a directory; expected their results as a CSV file")
    try:  # utf-8-sig: a spreadsheet's CSV may start with a byte-order mark
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not a text (UTF-8) CSV file: {error}") from None
    reader = csv.DictReader(io.StringIO(text, newline=""))
    header = [h.strip() for h in (reader.fieldnames or [])]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise ValueError(
            f"{path}: missing column {missing[0]!r}; the header must hold the columns "
            f"{', '.join(REQUIRED_COLUMNS)} (found: {', '.join(header) or 'nothing'})"
        )
    reader.fieldnames = header
    rows: dict[str, list] = {}
    known = {q.name: q for q in case.quantities}
    for line, row in enumerate(reader, start=2):
        name = (row.get("quantity") or "").strip()
        if name not in known:
            raise ValueError(
                f"{path}: line {line}, column quantity: {name!r} is not a quantity of case {case.name!r} "
                f"(quantities: {', '.join(known)})"
            )
        try:
            value = float(row["value"])
            x = float(row["x"]) if (row.get("x") or "").strip() else math.nan
        except (TypeError, ValueError):
            raise ValueError(
                f"{path}: line {line}: x = {row.get('x')!r}, value = {row.get('value')!r}: "
                "expected numbers (x empty for a scalar)"
            ) from None
        if not math.isfinite(value):
            raise ValueError(
                f"{path}: line {line}, column value: {row['value'].strip()!r}: expected a finite number"
            )
        x_text = (row.get("x") or "").strip()
        if known[name].kind == "curve" and not x_text:
            raise ValueError(
                f"{path}: line {line}, column x: empty for the curve {name!r}; expected its abscissa "
                f"{known[name].x} [{known[name].x_unit}]"
            )
        if known[name].kind == "curve" and not math.isfinite(x):
            raise ValueError(f"{path}: line {line}, column x: {x_text!r}: expected a finite number")
        if known[name].kind == "scalar" and x_text:
            raise ValueError(
                f"{path}: line {line}, column x: {x_text!r} for the scalar {name!r}; expected x empty"
            )
        rows.setdefault(name, []).append((x, value))
    absent = [name for name in known if name not in rows]
    if absent:
        raise ValueError(
            f"{path}: no rows for quantity {absent[0]!r} of case {case.name!r} (every quantity is needed: "
            f"{', '.join(known)})"
        )
    out = {}
    for name, samples in rows.items():
        quantity = known[name]
        data = np.array(samples, dtype=float)
        if quantity.kind == "scalar":
            if data.shape[0] != 1:
                raise ValueError(f"{path}: {data.shape[0]} rows for the scalar {name!r}; expected one")
            out[name] = data[:, 1]
            continue
        order = np.argsort(data[:, 0], kind="stable")
        values = sample_curve(data[order, 0], data[order, 1], quantity.at, where=f"{path}: quantity {name}")
        if not np.all(np.isfinite(values)):
            raise ValueError(
                f"{path}: quantity {name!r}: x covers [{data[:, 0].min():.6g}, {data[:, 0].max():.6g}] "
                f"{quantity.x_unit}; the reference samples it at {quantity.at[0]:.6g} to "
                f"{quantity.at[-1]:.6g}"
            )
        out[name] = values
    return out


def write_their_csv(case, values: dict, path) -> Path:
    """Write values of every quantity of ``case`` in the comparison format (columns quantity, x, value).

    Parameters
    ----------
    case : A :class:`refsim.reference.Case`.
    values : {quantity name: values at the case's sampling points, shape (k,), or a scalar}, e.g. from
        :func:`refsim.reference.case_values` of a results file.
    path : The CSV file to write.
    """
    lines = [",".join(REQUIRED_COLUMNS)]
    for quantity in case.quantities:
        data = np.atleast_1d(np.asarray(values[quantity.name], dtype=float))
        xs = quantity.at if quantity.kind == "curve" else ("",)
        for x, value in zip(xs, data, strict=True):
            lines.append(f"{quantity.name},{x if x == '' else f'{x:.12g}'},{value:.12g}")
    path = Path(path)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def compare(case_name: str, theirs, reference_folder) -> list[Comparison]:
    """Compare their results (a CSV file in the documented format, or a refsim results file .h5) with the
    reference of ``case_name`` in the package ``reference_folder``.

    Raises
    ------
    ValueError
        For an unknown case, a package without the case, or a malformed results file.
    """
    case = load_case(case_name)
    reference = read_case_reference(reference_folder, case.name)
    theirs = Path(theirs)
    if theirs.suffix.lower() in (".h5", ".hdf5"):
        if not theirs.is_file():
            raise ValueError(f"{theirs}: no such file")
        values = {k: np.atleast_1d(v) for k, v in case_values(case, theirs).items()}
    elif theirs.suffix.lower() == ".csv":
        values = read_their_csv(theirs, case)
    else:
        raise ValueError(f"{theirs}: expected a CSV file (.csv) or a refsim results file (.h5)")
    out = []
    for quantity in case.quantities:
        if quantity.name not in reference["quantities"]:
            raise ValueError(f"{reference['path']}: no quantity {quantity.name!r}; rebuild the package")
        ref = reference["quantities"][quantity.name]
        value, uncertainty, band = (
            np.atleast_1d(ref[k]).astype(float) for k in ("value", "uncertainty", "band")
        )
        mine = np.atleast_1d(values[quantity.name]).astype(float)
        difference = np.abs(mine - value)
        with np.errstate(divide="ignore", invalid="ignore"):
            error = np.where(difference == 0.0, 0.0, difference / uncertainty)
        out.append(
            Comparison(
                quantity=quantity.name,
                kind=quantity.kind,
                unit=quantity.unit,
                x_unit=quantity.x_unit,
                at=np.atleast_1d(ref["at"]).astype(float),
                reference=value,
                uncertainty=uncertainty,
                band=band,
                theirs=mine,
                error=error,
                passed=np.isfinite(difference) & (difference <= band),
            )
        )
    return out


def format_comparison(case_name: str, comparisons: list[Comparison]) -> str:
    """A plain-text table: per quantity, the worst sample's |d|/U and |d|/(U + T), and the verdict."""
    lines = [
        f"case {case_name}: pass when |theirs - reference| <= U + T",
        f"{'quantity':<24} {'samples':>7} {'worst |d|/U':>12} {'worst |d|/(U+T)':>16} {'failed':>7}  verdict",
    ]
    for item in comparisons:
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.abs(item.theirs - item.reference) / item.band
        worst_band = float(np.nanmax(ratio)) if np.any(np.isfinite(ratio)) else math.nan
        failed = int(np.count_nonzero(~item.passed))
        lines.append(
            f"{item.quantity:<24} {item.passed.size:>7} {float(np.nanmax(item.error)):>12.3g} "
            f"{worst_band:>16.3g} {failed:>7}  {'pass' if item.all_passed else 'FAIL'}"
        )
    return "\n".join(lines)


def comparison_figure(path, case_name: str, comparisons: list[Comparison]) -> Path:
    """Their values over the reference band (± U and ± (U + T)), one panel per quantity."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    case = load_case(case_name)
    figure, axes = plt.subplots(1, len(comparisons), figsize=(4.2 * len(comparisons), 3.4), squeeze=False)
    for axis, item in zip(axes[0], comparisons, strict=True):
        quantity = case.quantity(item.quantity)
        x = item.at if item.kind == "curve" else np.array([0.0])
        if item.kind == "scalar":
            x_band = np.array([-0.5, 0.5])
            value, band, u = (np.repeat(a, 2) for a in (item.reference, item.band, item.uncertainty))
        else:
            x_band, value, band, u = x, item.reference, item.band, item.uncertainty
        axis.fill_between(x_band, value - band, value + band, color="0.85", label="reference ± (U + T)")
        axis.fill_between(x_band, value - u, value + u, color="0.6", label="reference ± U")
        axis.plot(x_band, value, "k-", lw=1.2, label="reference")
        colours = np.where(item.passed, "tab:blue", "tab:red")
        axis.scatter(x, item.theirs, c=colours, s=18, zorder=3, label="theirs (red: outside)")
        if item.kind == "curve":
            axis.plot(x, item.theirs, "-", color="tab:blue", lw=0.8)
            axis.set_xlabel(f"{quantity.x} [{item.x_unit}]")
        else:
            axis.set_xticks([])
        axis.set_title(f"{item.quantity}: {'pass' if item.all_passed else 'FAIL'}", fontsize=9)
        axis.ticklabel_format(axis="both", style="sci", scilimits=(-2, 3))
        axis.tick_params(labelsize=7)
        axis.set_ylabel(f"[{item.unit}]")
        axis.legend(fontsize=6)
    figure.suptitle(f"{case.title}", fontsize=9)
    figure.tight_layout()
    path = Path(path)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path
