"""Rebuild the bundled MR.CLAM data (``mapmerge/data/mrclam/``) from the original files.

Usage::

    python tools/derive_mrclam.py ORIGINAL_DIR [--out mapmerge/data/mrclam]

``ORIGINAL_DIR`` holds dataset 7 of the UTIAS Multi-Robot Cooperative
Localization and Mapping data set in its original text format
(``Barcodes.dat``, ``Landmark_Groundtruth.dat`` and, for K = 1..5,
``RobotK_Odometry.dat``, ``RobotK_Measurement.dat``,
``RobotK_Groundtruth.dat``). Every bundled file is that file's own lines
(headers included, byte for byte), gzip-compressed, with two files thinned:

- ``RobotK_Odometry.dat``: of lines sharing one time stamp only the last
  is kept (the command that was in force afterwards), then only the lines
  whose commanded velocities differ from the line before, and the last
  line (it ends the log). The commands are held until the next line, so
  this is the same odometry, integrated exactly.
- ``RobotK_Groundtruth.dat`` (Vicon, about 60 Hz): the first line of every
  ``GROUNDTRUTH_STEP`` seconds from the first line on, and the last line.

The other files are complete. gzip is written with a zero time stamp so
that rebuilding gives the same bytes.
"""

from __future__ import annotations

import argparse
import gzip
from pathlib import Path

import numpy as np

#: Seconds between kept Vicon lines (the robots move at most about 0.3 m/s
#: and 0.6 rad/s: linear interpolation over 0.1 s errs by well under a millimetre).
GROUNDTRUTH_STEP = 0.1
N_ROBOTS = 5
OUT = Path(__file__).resolve().parents[1] / "mapmerge" / "data" / "mrclam"


def split(path: Path):
    """Header lines (``#``) and data lines of a file, with each data line's numbers."""
    lines = path.read_text().splitlines(keepends=True)
    header = [ln for ln in lines if ln.lstrip().startswith("#")]
    body = [ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
    return header, body, np.loadtxt(body, ndmin=2)


def thin_odometry(values: np.ndarray) -> np.ndarray:
    """Rows to keep: the last of each time stamp, then each change of command and the last row."""
    last_of_time = np.flatnonzero(np.r_[np.diff(values[:, 0]) > 0, True])
    cmd = values[last_of_time, 1:]
    changed = np.r_[True, np.any(np.diff(cmd, axis=0) != 0, axis=1)]
    changed[-1] = True
    return last_of_time[changed]


def thin_groundtruth(values: np.ndarray, step: float = GROUNDTRUTH_STEP) -> np.ndarray:
    """Rows to keep: the first of every ``step`` seconds and the last row."""
    slot = np.floor((values[:, 0] - values[0, 0]) / step).astype(np.int64)
    keep = np.r_[True, np.diff(slot) > 0]
    keep[-1] = True
    return np.flatnonzero(keep)


def write_gz(path: Path, lines) -> None:
    with open(path, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0, filename="") as fh:
        fh.write("".join(lines).encode())


def derive(source: Path, out: Path = OUT) -> dict:
    """Write the bundle from ``source`` into ``out``; returns lines kept per file."""
    out.mkdir(parents=True, exist_ok=True)
    kept = {}
    names = ["Barcodes.dat", "Landmark_Groundtruth.dat"]
    names += [f"Robot{k}_{kind}.dat" for k in range(1, N_ROBOTS + 1) for kind in ("Odometry", "Measurement", "Groundtruth")]
    for name in names:
        path = source / name
        if not path.is_file():
            raise SystemExit(f"missing original file: {path}")
        header, body, values = split(path)
        if name.endswith("_Odometry.dat"):
            rows = thin_odometry(values)
        elif name.endswith("_Groundtruth.dat") and name.startswith("Robot"):
            rows = thin_groundtruth(values)
        else:
            rows = np.arange(len(body))
        write_gz(out / f"{name}.gz", header + [body[i] for i in rows])
        kept[name] = (len(rows), len(body))
    return kept


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="directory of the original dataset-7 files")
    parser.add_argument("--out", type=Path, default=OUT, help=f"bundle directory (default {OUT})")
    args = parser.parse_args(argv)
    for name, (n, total) in derive(args.source, args.out).items():
        print(f"{name}: {n} of {total} lines")


if __name__ == "__main__":
    main()
