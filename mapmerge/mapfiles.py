"""Landmark maps as files: CSV or TSV with a header, or a pandas DataFrame.

A map file has one row per landmark and the columns

- ``x``, ``y`` (required): the landmark estimate in the map's own frame;
- ``id`` (optional): the landmark's name, carried into the combined map;
- ``sxx``, ``sxy``, ``syy`` (optional): its 2x2 covariance, or ``sigma``
  (optional): its per-coordinate standard deviation.

The file is UTF-8 text (a byte-order mark is fine); the separator is a
comma, or a tab when the file name ends in ``.tsv`` or the header holds tabs.
Reading and writing files needs numpy only; ``combined_table`` and
``group_table`` (DataFrames) need pandas.
"""

from __future__ import annotations

import csv
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._validation import MAX_MAGNITUDE, MIN_MAGNITUDE, first_out_of_range
from .result import MergeResult

if TYPE_CHECKING:
    import pandas as pd

COVARIANCE_COLUMNS = ("sxx", "sxy", "syy")


@dataclass(frozen=True)
class LandmarkMap:
    """A map read from a file.

    Attributes
    ----------
    points : (n, 2) ndarray
    ids : (n,) ndarray or None
        The ``id`` column, as read.
    cov : (n, 2, 2) ndarray or None
        Per-landmark covariances (from ``sxx, sxy, syy`` or ``sigma``).
    source : str
        Where the map came from (for messages).
    """

    points: np.ndarray
    ids: np.ndarray | None
    cov: np.ndarray | None
    source: str

    @property
    def variances(self) -> np.ndarray | None:
        """Per-coordinate variance of each landmark (half the covariance trace), or None."""
        return None if self.cov is None else np.trace(self.cov, axis1=1, axis2=2) / 2


class MapFileError(ValueError):
    """A map file or table that cannot be read as a landmark map."""


def read_map(source) -> LandmarkMap:
    """Read a landmark map from a CSV/TSV path or a DataFrame.

    Parameters
    ----------
    source : str, Path or pandas.DataFrame

    Returns
    -------
    LandmarkMap

    Raises
    ------
    MapFileError
        One line naming the file and what is wrong: missing file or column,
        a non-numeric or missing cell, fewer than 3 rows, a row with more
        cells than the header, a covariance that is not positive definite,
        an id given to two rows.
    """
    columns, name = _frame_columns(source) if _is_data_frame(source) else _file_columns(source)
    values = _numeric_columns(columns, name)
    ids = columns.get("id")
    if ids is not None:
        _check_unique_ids(ids, name)
    return LandmarkMap(points=np.column_stack([values["x"], values["y"]]), ids=ids,
                       cov=_covariances(values, name), source=name)


def _is_data_frame(source) -> bool:
    # Only pandas makes DataFrames: while it is not imported, ``source`` is not one (and CSV files need no pandas).
    pd = sys.modules.get("pandas")
    return pd is not None and isinstance(source, pd.DataFrame)


def _frame_columns(table) -> tuple[dict, str]:
    """The columns of a DataFrame by lower-case name (the first of a repeated name), as arrays."""
    columns = {}
    for column in table.columns:
        columns.setdefault(str(column).strip().lower(), table[column].to_numpy())
    return columns, "DataFrame"


def _file_columns(source) -> tuple[dict, str]:
    """The columns of a CSV/TSV file by lower-case name (the first of a repeated name), as object arrays of text."""
    path = Path(source)
    name = str(path)
    if not path.is_file():
        raise MapFileError(f"{name}: no such file")
    try:
        with open(path, encoding="utf-8") as fh:
            header = fh.readline()
        sep = "\t" if path.suffix.lower() == ".tsv" or "\t" in header else ","
        # utf-8-sig: a spreadsheet's byte-order mark is not part of the first column's name.
        with open(path, encoding="utf-8-sig", newline="") as fh:
            reader = csv.reader(fh, delimiter=sep)
            rows = []
            for row in reader:
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue  # a blank line (or one of spaces only, as pandas reads it)
                if rows and len(row) > len(rows[0]):
                    raise MapFileError(f"{name}: not a CSV/TSV table (line {reader.line_num} has {len(row)} "
                                       f"fields, the header {len(rows[0])})")
                rows.append(row)
    except UnicodeDecodeError as exc:
        raise MapFileError(f"{name}: not UTF-8 text (byte {exc.start}); save the map as UTF-8 CSV") from None
    except csv.Error as exc:
        raise MapFileError(f"{name}: not a CSV/TSV table ({exc})") from None
    if not rows:
        raise MapFileError(f"{name}: not a CSV/TSV table (the file is empty)")
    header, body = rows[0], rows[1:]
    columns = {}
    for k, column in enumerate(header):
        # A short row's missing cells are empty, as a spreadsheet shows them.
        cells = np.array([row[k] if k < len(row) else "" for row in body], dtype=object)
        columns.setdefault(column.strip().lower() or f"unnamed: {k}", cells)
    return columns, name


#: A cell of digits only: a column of them is read as integers, so ``-0`` is 0 (not -0.0).
_INTEGER = re.compile(r"[+-]?[0-9]+")


def _to_float(cells: np.ndarray) -> np.ndarray:
    """A column's cells as floats (NaN where a cell is not a number).

    Python's ``float`` also takes digit groups (``1_000``) and non-ASCII digits, which a map file's
    number never holds: those cells are not numbers here.
    """
    text = [str(cell).strip() for cell in cells]
    if text and all(_INTEGER.fullmatch(t) for t in text):
        return np.array([float(int(t)) for t in text], dtype=float)
    out = np.full(len(text), np.nan)
    for k, t in enumerate(text):
        if t.isascii() and "_" not in t:
            try:
                out[k] = float(t)
            except ValueError:
                pass
    return out


def _numeric_columns(columns: dict, name: str) -> dict:
    """x, y and the covariance or sigma columns as float arrays, after the checks of the table's shape."""
    missing = [c for c in ("x", "y") if c not in columns]
    if missing and len(columns) == 1 and ";" in next(iter(columns)):
        raise MapFileError(f"{name}: columns separated by ';'; map files are comma- or tab-separated "
                           "(with a decimal point)")
    if missing:
        raise MapFileError(f"{name}: missing column {', '.join(missing)} (have: {', '.join(columns)})")
    n_rows = len(columns["x"])
    if n_rows < 3:
        raise MapFileError(f"{name}: needs at least 3 landmarks (rows), got {n_rows}")
    has_cov = [c for c in COVARIANCE_COLUMNS if c in columns]
    if has_cov and len(has_cov) != 3:
        raise MapFileError(f"{name}: covariance needs all of sxx, sxy, syy, got only {', '.join(has_cov)}")
    numeric = ["x", "y", *has_cov, *(["sigma"] if "sigma" in columns and not has_cov else [])]
    values = {}
    for col in numeric:
        v = _to_float(columns[col])
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise MapFileError(f"{name}: column {col} row {bad[0] + 1} is {columns[col][bad[0]]!r}, "
                               "not a finite number")
        values[col] = v
    return values


def _covariances(values: dict, name: str) -> np.ndarray | None:
    """Per-landmark covariances from ``sxx, sxy, syy`` or ``sigma`` (None without either), checked."""
    if "sxx" in values:
        cov = np.stack([np.stack([values["sxx"], values["sxy"]], -1), np.stack([values["sxy"], values["syy"]], -1)], -2)
        bad = np.flatnonzero((values["sxx"] <= 0) | (values["sxx"] * values["syy"] - values["sxy"] ** 2 <= 0))
        if bad.size:
            raise MapFileError(f"{name}: row {bad[0] + 1}: covariance (sxx, sxy, syy) must be positive definite")
        _check_range(np.sqrt(np.stack([values["sxx"], values["syy"]], axis=1)), name,
                     f"sxx and syy must lie in [{MIN_MAGNITUDE**2:g}, {MAX_MAGNITUDE**2:g}]")
        return cov
    if "sigma" in values:
        bad = np.flatnonzero(values["sigma"] <= 0)
        if bad.size:
            raise MapFileError(f"{name}: row {bad[0] + 1}: sigma must be > 0")
        _check_range(values["sigma"], name, f"sigma must lie in [{MIN_MAGNITUDE:g}, {MAX_MAGNITUDE:g}]")
        return (values["sigma"] ** 2)[:, None, None] * np.eye(2)
    return None


def _check_unique_ids(ids: np.ndarray, name: str) -> None:
    """A MapFileError naming the first id (ignoring blanks) given to two rows."""
    # An id names one landmark: a repeated one would join two rows of the combined map to one name.
    named = [str(v).strip() for v in ids]
    rows_of: dict[str, list[int]] = {}
    for row, v in enumerate(named):
        if v != "":
            rows_of.setdefault(v, []).append(row)
    repeated = [rows for rows in rows_of.values() if len(rows) > 1]
    if repeated:
        # The id of the first row whose id is repeated.
        rows = min(repeated)
        raise MapFileError(f"{name}: id {named[rows[0]]!r} is repeated (rows {rows[0] + 1} and "
                           f"{rows[1] + 1}); ids must be unique")


def _check_range(sd: np.ndarray, name: str, rule: str) -> None:
    """A MapFileError naming the first row whose standard deviations ``sd`` leave the range ``merge_maps``
    accepts (``rule`` says it)."""
    row = first_out_of_range(sd)
    if row is not None:
        raise MapFileError(f"{name}: row {row + 1}: {rule} (rescale the map's units)")


def combined_table(result: MergeResult, map_p: LandmarkMap | None = None,
                   map_q: LandmarkMap | None = None) -> pd.DataFrame:
    """The combined map as a table: x, y, origin, index_p, index_q[, id_p, id_q], sxx, sxy, syy.

    ``index_p``/``index_q`` are 0-based rows of the input maps (-1: none). Needs pandas
    (``write_map`` does not).

    Raises
    ------
    ValueError
        If ``result`` is not a ``MergeResult`` or a map is not the ``LandmarkMap`` that was merged.
    """
    import pandas as pd

    return pd.DataFrame(_combined_columns(result, map_p, map_q))


def _combined_columns(result: MergeResult, map_p: LandmarkMap | None, map_q: LandmarkMap | None) -> dict:
    """The columns of ``combined_table``, by name in order, as arrays."""
    if not isinstance(result, MergeResult):
        raise ValueError(f"result must be the MergeResult of merge_maps, got {type(result).__name__}")
    c = result.combined
    for side, m, index in (("p", map_p, c.index_p), ("q", map_q, c.index_q)):
        if m is not None and not (isinstance(m, LandmarkMap) and index.max(initial=-1) < len(m.points)):
            raise ValueError(f"map_{side} must be the LandmarkMap (read_map) whose landmarks were merged as "
                             f"{side}, with at least {index.max(initial=-1) + 1} rows")
    table = {"x": c.points[:, 0], "y": c.points[:, 1], "origin": c.origin.astype(str),
             "index_p": c.index_p, "index_q": c.index_q}
    for side, m, index in (("p", map_p, c.index_p), ("q", map_q, c.index_q)):
        if m is not None and m.ids is not None:
            table[f"id_{side}"] = np.where(index >= 0, m.ids[np.maximum(index, 0)], "")
    cov = result.cov
    table["sxx"], table["sxy"], table["syy"] = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    return table


def write_map(result: MergeResult, path, map_p: LandmarkMap | None = None, map_q: LandmarkMap | None = None):
    """Write the combined map of ``result`` (``combined_table``) as CSV, or TSV for a ``.tsv`` name.

    Numbers are written in full (the shortest text that reads back as the same
    float): map coordinates such as UTM eastings or degrees need every digit."""
    return _write_columns(_combined_columns(result, map_p, map_q), path)


def group_table(group, maps: list[LandmarkMap]):
    """The fused map of ``merge_many`` as a table: x, y, n_maps, index_0 .. index_{N-1}[, id_k], sxx, sxy, syy.

    ``index_k`` is the 0-based row of the landmark in map k (-1: not in it), ``n_maps`` how many maps
    hold it; ``id_k`` is map k's ``id`` column where it has one. Needs pandas (``write_group`` does not).

    Raises
    ------
    ValueError
        If ``maps`` are not the ``LandmarkMap`` list that was merged.
    """
    import pandas as pd

    return pd.DataFrame(_group_columns(group, maps))


def _group_columns(group, maps: list[LandmarkMap]) -> dict:
    """The columns of ``group_table``, by name in order, as arrays."""
    tracks = group.tracks
    if len(maps) != tracks.shape[1] or any(not isinstance(m, LandmarkMap) or tracks[:, k].max(initial=-1)
                                           >= len(m.points) for k, m in enumerate(maps)):
        raise ValueError(f"maps must be the {tracks.shape[1]} LandmarkMap (read_map) that were merged")
    table = {"x": group.merged[:, 0], "y": group.merged[:, 1], "n_maps": (tracks >= 0).sum(axis=1)}
    for k, m in enumerate(maps):
        table[f"index_{k}"] = tracks[:, k]
        if m.ids is not None:
            table[f"id_{k}"] = np.where(tracks[:, k] >= 0, m.ids[np.maximum(tracks[:, k], 0)], "")
    cov = group.merged_cov
    table["sxx"], table["sxy"], table["syy"] = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    return table


def write_group(group, path, maps: list[LandmarkMap]):
    """Write ``group_table`` as CSV, or TSV for a ``.tsv`` name (numbers in full, as ``write_map``)."""
    return _write_columns(_group_columns(group, maps), path)


def _cell(value) -> str:
    # The shortest text that reads back as the same float (float's own repr: numpy's names the type);
    # an empty cell for a missing value, as pandas writes one.
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if value != value else float.__repr__(value)
    return str(value)


def _write_columns(columns: dict, path) -> Path:
    """Write named columns as CSV, or TSV for a ``.tsv`` name, one line per row (UTF-8, minimal quoting)."""
    path = Path(path)
    with open(path, "w", encoding="utf-8", newline="") as fh:
        writer = csv.writer(fh, delimiter="\t" if path.suffix.lower() == ".tsv" else ",", lineterminator=os.linesep)
        writer.writerow(columns)
        writer.writerows([_cell(v) for v in row] for row in zip(*(np.asarray(c).tolist() for c in columns.values())))
    return path
