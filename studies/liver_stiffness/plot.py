"""Figure of the liver stiffness study: q_max(E) per amplitude against G_c, and the critical modulus E_c(a).

python studies/liver_stiffness/plot.py [--output studies/liver_stiffness/output]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
#: The published G_c of liver the scenes cite [J/m²] (refsim/scenes/liver_rigid.toml).
PUBLISHED = (76.0, 225.0)


def critical_modulus(moduli: np.ndarray, loads: np.ndarray, threshold: float) -> float:
    """E where q(E) crosses the threshold, interpolated linearly in log E (nan when it does not cross)."""
    order = np.argsort(moduli)
    moduli, loads = np.asarray(moduli)[order], np.asarray(loads)[order]
    above = np.flatnonzero(loads >= threshold)
    if above.size == 0 or above[0] == 0:
        return float("nan")
    i = above[0]
    x0, x1 = np.log(moduli[i - 1]), np.log(moduli[i])
    return float(np.exp(x0 + (threshold - loads[i - 1]) / (loads[i] - loads[i - 1]) * (x1 - x0)))


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=ROOT / "studies" / "liver_stiffness" / "output")
    args = parser.parse_args(argv)
    rows = json.loads((args.output / "summary.json").read_text())["rows"]
    g_c = rows[0]["fracture_energy"]
    amplitudes = sorted({r["amplitude"] for r in rows})
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    critical = []
    for amplitude in amplitudes:
        mine = sorted((r for r in rows if r["amplitude"] == amplitude), key=lambda r: r["youngs_modulus"])
        moduli = np.array([r["youngs_modulus"] for r in mine])
        loads = np.array([r["q_max"] for r in mine])
        left.semilogx(moduli / 1e9, loads, "o-", label=f"a = {amplitude * 1e3:g} mm")
        critical.append(critical_modulus(moduli, loads, g_c))
    left.axhline(g_c, color="k", ls="--", label=f"G_c = {g_c:g} J/m² (the scenes)")
    left.axhspan(*PUBLISHED, color="0.9", zorder=0, label="published G_c of liver")
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    left.set_xticks(sorted({r["youngs_modulus"] / 1e9 for r in rows}))
    left.xaxis.set_major_formatter(ScalarFormatter())
    left.xaxis.set_minor_formatter(NullFormatter())
    left.set_xlabel("needle modulus E [GPa]")
    left.set_ylabel("largest shaft load per length q [N/m]")
    left.legend()
    right.set_title("needles stiffer than E_c cut")
    if np.any(np.isfinite(critical)):
        right.plot(np.array(amplitudes) * 1e3, np.array(critical) / 1e9, "s-")
        right.set_xlabel("breathing amplitude [mm]")
        right.set_ylabel("critical modulus E_c [GPa]")
    else:  # no modulus reaches G_c: say so instead of an empty axis
        largest = max(rows, key=lambda r: r["q_max"])
        right.axis("off")
        right.text(
            0.5,
            0.5,
            f"no critical modulus up to {max(r['youngs_modulus'] for r in rows) / 1e9:g} GPa\n"
            f"at any amplitude: the largest load is {largest['q_max']:.1f} N/m\n"
            f"(a = {largest['amplitude'] * 1e3:g} mm, E = {largest['youngs_modulus'] / 1e9:g} GPa),\n"
            f"below G_c = {g_c:g} J/m²",
            ha="center",
            va="center",
            transform=right.transAxes,
        )
    figure.tight_layout()
    out = ROOT / "docs" / "figures" / "liver_stiffness.png"
    figure.savefig(out, dpi=120)
    for amplitude, value in zip(amplitudes, critical, strict=False):
        print(f"a = {amplitude * 1e3:g} mm: E_c = {value / 1e9:.3g} GPa")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
