"""Compare two refsim results files dataset by dataset, ignoring wall-clock data.

    python studies/regression/compare.py A.h5 B.h5 [--atol 0]

Prints, for each dataset, "same", the largest absolute difference, or why the two differ (shape, missing), and
exits 1 when any dataset differs by more than ``--atol``. Used to show that a refactoring changed no result.
"""

from __future__ import annotations

import argparse
import sys

import h5py
import numpy as np

# Wall-clock data: seconds spent, creation time, commit.
IGNORED = ("solver/seconds", "steps/stage_seconds", "steps/triangulation_seconds")
IGNORED_ATTRIBUTES = ("created", "git_commit", "refsim_version")


def datasets(handle: h5py.File) -> dict[str, h5py.Dataset]:
    found: dict[str, h5py.Dataset] = {}
    handle.visititems(
        lambda name, obj: found.__setitem__(name, obj) if isinstance(obj, h5py.Dataset) else None
    )
    return found


def compare(path_a: str, path_b: str, atol: float = 0.0) -> list[tuple[str, str]]:
    """(dataset, verdict) for every dataset of either file; verdict "same" or a description."""
    out = []
    with h5py.File(path_a, "r") as a, h5py.File(path_b, "r") as b:
        for key in sorted(set(a.attrs) | set(b.attrs)):
            if key in IGNORED_ATTRIBUTES:
                continue
            same = key in a.attrs and key in b.attrs and str(a.attrs[key]) == str(b.attrs[key])
            out.append((f"@{key}", "same" if same else "differs"))
        da, db = datasets(a), datasets(b)
        for name in sorted(set(da) | set(db)):
            if name in IGNORED or name.endswith("/seconds"):
                continue
            if name not in da or name not in db:
                out.append((name, f"only in {'A' if name in da else 'B'}"))
                continue
            x, y = da[name][()], db[name][()]
            if x.shape != y.shape:
                out.append((name, f"shape {x.shape} vs {y.shape}"))
            elif x.dtype.kind in "fc":
                nan_same = np.array_equal(np.isnan(x), np.isnan(y))
                both = ~(np.isnan(x) | np.isnan(y))
                diff = float(np.max(np.abs(x[both] - y[both]), initial=0.0))
                out.append((name, "same" if (diff <= atol and nan_same) else f"max |diff| {diff:.3e}"))
            else:
                out.append((name, "same" if np.array_equal(x, y) else "differs"))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a")
    parser.add_argument("b")
    parser.add_argument("--atol", type=float, default=0.0)
    args = parser.parse_args(argv)
    rows = compare(args.a, args.b, args.atol)
    bad = [(n, v) for n, v in rows if v != "same"]
    for name, verdict in rows:
        if verdict != "same":
            print(f"{name}: {verdict}")
    print(f"{len(rows) - len(bad)} of {len(rows)} datasets and attributes identical")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
