"""Landmark maps as files: CSV or TSV with a header, or a pandas DataFrame.

A map file has one row per landmark and the columns

- ``x``, ``y`` (required): the landmark estimate in the map's own frame;
- ``id`` (optional): the landmark's name, carried into the combined map;
- ``sxx``, ``sxy``, ``syy`` (optional): its 2x2 covariance, or ``sigma``
  (optional): its per-coordinate standard deviation.

The file is UTF-8 text (a byte-order mark is fine); the separator is a
comma, or a tab when the file name ends in ``.tsv`` or the header holds tabs.
"""

from __future__ import annotations

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
        a non-numeric or missing cell, fewer than 3 rows, a covariance that
        is not positive definite, an id given to two rows.
    """
    import pandas as pd  # here, not at the top: ``import mapmerge`` need not load pandas

    if isinstance(source, pd.DataFrame):
        table, name = source, "DataFrame"
    else:
        path = Path(source)
        name = str(path)
        if not path.is_file():
            raise MapFileError(f"{name}: no such file")
        try:
            with open(path, encoding="utf-8") as fh:
                header = fh.readline()
            sep = "\t" if path.suffix.lower() == ".tsv" or "\t" in header else ","
            table = pd.read_csv(path, sep=sep, dtype=str, keep_default_na=False, encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise MapFileError(f"{name}: not UTF-8 text (byte {exc.start}); save the map as UTF-8 CSV") from None
        except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
            raise MapFileError(f"{name}: not a CSV/TSV table ({str(exc).splitlines()[0]})") from None
    table = table.rename(columns=lambda c: str(c).strip().lower())
    missing = [c for c in ("x", "y") if c not in table.columns]
    if missing and len(table.columns) == 1 and ";" in str(table.columns[0]):
        raise MapFileError(f"{name}: columns separated by ';'; map files are comma- or tab-separated "
                           "(with a decimal point)")
    if missing:
        raise MapFileError(f"{name}: missing column {', '.join(missing)} (have: {', '.join(map(str, table.columns))})")
    if len(table) < 3:
        raise MapFileError(f"{name}: needs at least 3 landmarks (rows), got {len(table)}")
    has_cov = [c for c in COVARIANCE_COLUMNS if c in table.columns]
    if has_cov and len(has_cov) != 3:
        raise MapFileError(f"{name}: covariance needs all of sxx, sxy, syy, got only {', '.join(has_cov)}")
    numeric = ["x", "y", *has_cov, *(["sigma"] if "sigma" in table.columns and not has_cov else [])]
    values = {}
    for col in numeric:
        v = pd.to_numeric(table[col].astype(str).str.strip(), errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            cell = table[col].iloc[bad[0]]
            raise MapFileError(f"{name}: column {col} row {bad[0] + 1} is {cell!r}, not a finite number")
        values[col] = v
    cov = None
    if has_cov:
        cov = np.stack([np.stack([values["sxx"], values["sxy"]], -1), np.stack([values["sxy"], values["syy"]], -1)], -2)
        bad = np.flatnonzero((values["sxx"] <= 0) | (values["sxx"] * values["syy"] - values["sxy"] ** 2 <= 0))
        if bad.size:
            raise MapFileError(f"{name}: row {bad[0] + 1}: covariance (sxx, sxy, syy) must be positive definite")
        _check_range(np.sqrt(np.stack([values["sxx"], values["syy"]], axis=1)), name,
                     f"sxx and syy must lie in [{MIN_MAGNITUDE**2:g}, {MAX_MAGNITUDE**2:g}]")
    elif "sigma" in values:
        bad = np.flatnonzero(values["sigma"] <= 0)
        if bad.size:
            raise MapFileError(f"{name}: row {bad[0] + 1}: sigma must be > 0")
        _check_range(values["sigma"], name, f"sigma must lie in [{MIN_MAGNITUDE:g}, {MAX_MAGNITUDE:g}]")
        cov = (values["sigma"] ** 2)[:, None, None] * np.eye(2)
    ids = table["id"].to_numpy() if "id" in table.columns else None
    if ids is not None:
        # An id names one landmark: a repeated one would join two rows of the combined map to one name.
        named = pd.Series(ids).astype(str).str.strip()
        repeated = np.flatnonzero(named.duplicated(keep=False).to_numpy() & (named != "").to_numpy())
        if repeated.size:
            rows = np.flatnonzero(named.to_numpy() == named.iloc[repeated[0]])
            raise MapFileError(f"{name}: id {named.iloc[repeated[0]]!r} is repeated (rows {rows[0] + 1} and "
                               f"{rows[1] + 1}); ids must be unique")
    return LandmarkMap(points=np.column_stack([values["x"], values["y"]]), ids=ids, cov=cov, source=name)


def _check_range(sd: np.ndarray, name: str, rule: str) -> None:
    """A MapFileError naming the first row whose standard deviations ``sd`` leave the range ``merge_maps``
    accepts (``rule`` says it)."""
    row = first_out_of_range(sd)
    if row is not None:
        raise MapFileError(f"{name}: row {row + 1}: {rule} (rescale the map's units)")


def combined_table(result: MergeResult, map_p: LandmarkMap | None = None,
                   map_q: LandmarkMap | None = None) -> pd.DataFrame:
    """The combined map as a table: x, y, origin, index_p, index_q[, id_p, id_q], sxx, sxy, syy.

    ``index_p``/``index_q`` are 0-based rows of the input maps (-1: none).

    Raises
    ------
    ValueError
        If ``result`` is not a ``MergeResult`` or a map is not the ``LandmarkMap`` that was merged.
    """
    import pandas as pd

    if not isinstance(result, MergeResult):
        raise ValueError(f"result must be the MergeResult of merge_maps, got {type(result).__name__}")
    c = result.combined
    for side, m, index in (("p", map_p, c.index_p), ("q", map_q, c.index_q)):
        if m is not None and not (isinstance(m, LandmarkMap) and index.max(initial=-1) < len(m.points)):
            raise ValueError(f"map_{side} must be the LandmarkMap (read_map) whose landmarks were merged as "
                             f"{side}, with at least {index.max(initial=-1) + 1} rows")
    table = pd.DataFrame({"x": c.points[:, 0], "y": c.points[:, 1], "origin": c.origin.astype(str),
                          "index_p": c.index_p, "index_q": c.index_q})
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
    path = Path(path)
    combined_table(result, map_p, map_q).to_csv(path, index=False, sep="\t" if path.suffix.lower() == ".tsv" else ",")
    return path


def group_table(group, maps: list[LandmarkMap]):
    """The fused map of ``merge_many`` as a table: x, y, n_maps, index_0 .. index_{N-1}[, id_k], sxx, sxy, syy.

    ``index_k`` is the 0-based row of the landmark in map k (-1: not in it), ``n_maps`` how many maps
    hold it; ``id_k`` is map k's ``id`` column where it has one.

    Raises
    ------
    ValueError
        If ``maps`` are not the ``LandmarkMap`` list that was merged.
    """
    import pandas as pd

    tracks = group.tracks
    if len(maps) != tracks.shape[1] or any(not isinstance(m, LandmarkMap) or tracks[:, k].max(initial=-1)
                                           >= len(m.points) for k, m in enumerate(maps)):
        raise ValueError(f"maps must be the {tracks.shape[1]} LandmarkMap (read_map) that were merged")
    table = pd.DataFrame({"x": group.merged[:, 0], "y": group.merged[:, 1], "n_maps": (tracks >= 0).sum(axis=1)})
    for k, m in enumerate(maps):
        table[f"index_{k}"] = tracks[:, k]
        if m.ids is not None:
            table[f"id_{k}"] = np.where(tracks[:, k] >= 0, m.ids[np.maximum(tracks[:, k], 0)], "")
    cov = group.merged_cov
    table["sxx"], table["sxy"], table["syy"] = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    return table


def write_group(group, path, maps: list[LandmarkMap]):
    """Write ``group_table`` as CSV, or TSV for a ``.tsv`` name (numbers in full, as ``write_map``)."""
    path = Path(path)
    group_table(group, maps).to_csv(path, index=False, sep="\t" if path.suffix.lower() == ".tsv" else ",")
    return path
