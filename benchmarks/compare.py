"""Regression comparison of two results CSVs (``meshbench compare``).

Rows are matched on their *key* columns; every other numeric column is a *value* compared
with ``|new - old| <= atol + rtol * |old|`` (NaN equals NaN). Columns of provenance that
legitimately differ between machines and runs (wall times, peak memory, git SHA, library
versions, timestamps, device, threads) are ignored by default.

Keys default to the columns that are not floating point (ids, seeds, trajectory and step
indices); pass ``keys`` to choose them. Exit codes of the command: 0 within tolerance,
1 regression, 2 malformed input (unreadable file, missing columns, duplicate keys, rows
present in one file only).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

DEFAULT_IGNORE = re.compile(
    r"(wall|peak_mem|_time_s$|git_sha|timestamp|created|device|threads|hostname|platform|"
    r"version|^python$|^numpy$|^scipy$|^torch|^pandas$|^meshio$|^scikit.fem$)")


class CompareError(ValueError):
    """The files cannot be compared (exit code 2)."""


@dataclass
class CompareResult:
    keys: list
    values: list
    ignored: list
    n_rows: int
    moved: pd.DataFrame = field(default_factory=pd.DataFrame)

    @property
    def ok(self) -> bool:
        return self.moved.empty


def read_csv(path) -> pd.DataFrame:
    try:
        df = pd.read_csv(path, comment="#")
    except FileNotFoundError:
        raise CompareError(f"{path}: no such file") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
        raise CompareError(f"{path}: not a readable CSV ({e})") from None
    if df.columns.duplicated().any():
        raise CompareError(f"{path}: duplicate column names {list(df.columns[df.columns.duplicated()])}")
    return df


def compare(old: pd.DataFrame, new: pd.DataFrame, rtol: float = 1e-6, atol: float = 0.0,
            keys=None, ignore=(), default_ignore: bool = True,
            names=("baseline", "new")) -> CompareResult:
    """Match rows on key columns and report values that moved beyond tolerance."""
    if rtol < 0 or atol < 0 or not np.isfinite(rtol) or not np.isfinite(atol):
        raise CompareError(f"rtol and atol must be finite and >= 0, got rtol={rtol}, atol={atol}")
    ignored = [c for c in old.columns if c in set(ignore)
               or (default_ignore and DEFAULT_IGNORE.search(c) and c not in (keys or ()))]
    missing_new = [c for c in old.columns if c not in new.columns and c not in ignored]
    missing_old = [c for c in new.columns if c not in old.columns and c not in ignored]
    if missing_new or missing_old:
        raise CompareError(f"columns differ: missing from {names[1]}: {missing_new}; "
                           f"missing from {names[0]}: {missing_old}")
    cols = [c for c in old.columns if c not in ignored]
    if keys is None:
        keys = [c for c in cols if not pd.api.types.is_float_dtype(old[c])]
    bad = [k for k in keys if k not in cols]
    if bad:
        raise CompareError(f"key columns {bad} are not in both files; columns: {cols}")
    if not keys:
        raise CompareError("no key columns: pass --keys to say which columns identify a row")
    values = [c for c in cols if c not in keys]
    for df, name in ((old, names[0]), (new, names[1])):
        dup = df[df.duplicated(subset=keys, keep=False)]
        if not dup.empty:
            raise CompareError(f"{name}: duplicate keys {keys}, e.g. "
                               f"{dup[keys].head(3).to_dict('records')}")
    o, n = (df[keys + values].astype({k: str for k in keys}) for df in (old, new))
    merged = o.merge(n, on=keys, how="outer", suffixes=("_old", "_new"), indicator=True)
    only = merged[merged["_merge"] != "both"]
    if not only.empty:
        side = only["_merge"].map({"left_only": f"only in {names[0]}",
                                   "right_only": f"only in {names[1]}"})
        rows = [f"{s}: {r}" for s, r in zip(side, only[keys].head(5).to_dict("records"))]
        raise CompareError(f"{len(only)} rows are present in one file only: " + "; ".join(rows))
    moved = []
    for c in values:
        a, b = merged[f"{c}_old"], merged[f"{c}_new"]
        if pd.api.types.is_numeric_dtype(a) and pd.api.types.is_numeric_dtype(b):
            a, b = a.to_numpy(float), b.to_numpy(float)
            close = np.isclose(b, a, rtol=rtol, atol=atol, equal_nan=True)
        else:
            close = (a.astype(str) == b.astype(str)).to_numpy()
        for i in np.flatnonzero(~close):
            row = {k: merged[k].iloc[i] for k in keys}
            old_v, new_v = merged[f"{c}_old"].iloc[i], merged[f"{c}_new"].iloc[i]
            rel = _rel(old_v, new_v)
            moved.append({**row, "column": c, "old": old_v, "new": new_v, "rel_change": rel})
    return CompareResult(keys, values, ignored, len(merged), pd.DataFrame(moved))


def _rel(a, b):
    try:
        a, b = float(a), float(b)
    except (TypeError, ValueError):
        return float("nan")
    return (b - a) / abs(a) if a != 0 else (0.0 if b == 0 else float("inf"))
