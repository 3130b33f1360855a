"""The bench scripts' results files: each run appends its table (header lines and rows) to a text file in
bench/results/, so that earlier runs stay beside the new one."""
from __future__ import annotations

from pathlib import Path


def append_table(out, lines: list[str]) -> Path:
    """Append `lines` and a blank line to the file `out` (its folder made if missing); say where."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "a") as f:
        f.write("\n".join(lines) + "\n\n")
    print(f"appended to {out}")
    return out
