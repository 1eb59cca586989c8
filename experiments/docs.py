"""Copy result tables into the docs between markers.

    python -m experiments.docs

A block ``<!-- include: results/x.md -->`` ... ``<!-- end include -->`` in
README.md or docs/*.md is replaced by the current content of
``results/x.md`` (its first ``# `` title line dropped, ``## `` sections
demoted to ``#### ``, links to sibling files made relative to the page), so
the numbers on those pages are always the ones the commands wrote.
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

BLOCK = re.compile(r"(<!-- include: (?P<path>\S+) -->\n)(?P<body>.*?)(<!-- end include -->)", re.S)


def refresh(readme: Path, root: Path | None = None) -> list[str]:
    """Rewrite every include block of ``readme`` (paths relative to ``root``,
    default the page's folder); return the files included."""
    root = readme.parent if root is None else root
    used = []

    def fill(m: re.Match) -> str:
        path = root / m["path"]
        text = path.read_text()
        # The file's title goes; its sections become sub-sections of the README's.
        lines = ["##" + line if line.startswith("## ") else line
                 for line in text.splitlines() if not line.startswith("# ")]
        # Links to sibling files (e.g. a figure next to the table).
        rel = Path(os.path.relpath(path.parent, readme.parent))
        body = re.sub(r"\]\((?!https?:|/)([^)]+)\)", lambda k: f"]({(rel / k[1]).as_posix()})",
                      "\n".join(lines).strip())
        used.append(m["path"])
        return f"{m[1]}{body}\n{m[4]}"

    readme.write_text(BLOCK.sub(fill, readme.read_text()))
    return used


def main(argv=None) -> None:
    argparse.ArgumentParser(description="Copy the result tables into README.md and docs/*.md "
                                        "(every include block).").parse_args(argv)
    root = Path(__file__).resolve().parent.parent
    for page in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        for path in refresh(page, root):
            print(f"{page.relative_to(root)}: {path}")


if __name__ == "__main__":
    main()
