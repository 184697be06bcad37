"""The anthropometric surveys as arrays in our names and units: ANSUR II and NHANES 2017-2020 tables.

ANSUR II (C. C. Gordon et al., "2012 Anthropometric Survey of U.S. Army Personnel: Methods and Summary
Statistics", NATICK/TR-15/007, 2014) gives millimetres and tenths of a kilogram under the column names our
measurements take; NHANES 2017-2020 P_BMX (US Centers for Disease Control and Prevention, National Health
and Nutrition Examination Survey) gives centimetres and kilograms. Both are public domain (US Government
works); the provenance of the copies is in tests/data/anthropometry/SOURCES.md.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from bodyfit.models.anthropometry.definitions import MEASUREMENTS

# NHANES column -> our measurement name.
NHANES_COLUMNS = {m.nhanes: name for name, m in MEASUREMENTS.items() if m.nhanes}


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, encoding="latin-1", newline="") as f:
        rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
    return [h.strip() for h in rows[0]], rows[1:]


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return float("nan")


def read_ansur(path: str | Path) -> dict[str, np.ndarray]:
    """An ANSUR II table: our measurement name -> (N,) float64 in metres (kilograms for ``weightkg``), for
    every measurement the table has, plus ``subjectid`` (N,) and ``sex`` (N,) ("male" / "female")."""
    header, rows = _rows(Path(path))
    out: dict[str, np.ndarray] = {}
    for name, m in MEASUREMENTS.items():
        if m.ansur in header:
            i = header.index(m.ansur)
            scale = 0.1 if m.kind == "mass" else 0.001
            out[name] = np.array([_number(r[i]) for r in rows]) * scale
    idx = header.index("subjectid") if "subjectid" in header else header.index("SubjectId")
    out["subjectid"] = np.array([int(r[idx]) for r in rows])
    gender = header.index("Gender")
    out["sex"] = np.array([r[gender].strip().lower() for r in rows])
    return out


def read_nhanes(path: str | Path) -> dict[str, np.ndarray]:
    """An NHANES P_BMX table (the adult male or female extract): our measurement name -> (N,) float64 in
    metres and kilograms, NaN where not measured, for the columns in :data:`NHANES_COLUMNS`."""
    header, rows = _rows(Path(path))
    out = {}
    for column, name in NHANES_COLUMNS.items():
        if column in header:
            i = header.index(column)
            scale = 1.0 if MEASUREMENTS[name].kind == "mass" else 0.01
            out[name] = np.array([_number(r[i]) for r in rows]) * scale
    return out
