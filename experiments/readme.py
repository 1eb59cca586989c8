"""Copy result tables into README.md between markers.

    python -m experiments.readme

A block ``<!-- include: results/x.md -->`` ... ``<!-- end include -->`` in
README.md is replaced by the current content of ``results/x.md`` (its
first ``# `` title line dropped, ``## `` sections demoted to ``#### ``,
links to sibling files made relative to the repository root), so the README's numbers are always the ones the
commands wrote.
"""

from __future__ import annotations

import re
from pathlib import Path

BLOCK = re.compile(r"(<!-- include: (?P<path>\S+) -->\n)(?P<body>.*?)(<!-- end include -->)", re.S)


def refresh(readme: Path) -> list[str]:
    """Rewrite every include block of ``readme``; return the files included."""
    root = readme.parent
    used = []

    def fill(m: re.Match) -> str:
        path = root / m["path"]
        text = path.read_text()
        # The file's title goes; its sections become sub-sections of the README's.
        lines = ["##" + line if line.startswith("## ") else line
                 for line in text.splitlines() if not line.startswith("# ")]
        # Links to sibling files (e.g. a figure next to the table).
        body = re.sub(r"\]\((?!https?:|/)([^)]+)\)", lambda k: f"]({path.parent.relative_to(root) / k[1]})",
                      "\n".join(lines).strip())
        used.append(m["path"])
        return f"{m[1]}{body}\n{m[4]}"

    readme.write_text(BLOCK.sub(fill, readme.read_text()))
    return used


def main() -> None:
    for path in refresh(Path(__file__).resolve().parent.parent / "README.md"):
        print(path)


if __name__ == "__main__":
    main()
