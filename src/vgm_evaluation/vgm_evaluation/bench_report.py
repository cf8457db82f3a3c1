"""How a bench leaves what it measured: one directory per bench under bench/results/, each
result twice, as Markdown to read (and quote in a README) and as JSON to compare runs, and
figures as PNG beside them.

The benches call these three functions instead of each writing its own table and file code.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def markdown_table(columns: Sequence[str], rows: Iterable[Sequence[object]]) -> list[str]:
    """The lines of a Markdown table; cells are written with ``str`` (format them first)."""
    lines = ['| ' + ' | '.join(columns) + ' |', '|' + '---|' * len(columns)]
    for row in rows:
        if len(row) != len(columns):
            raise ValueError(f'a row of {len(row)} cells under {len(columns)} columns: {row}')
        lines.append('| ' + ' | '.join(str(cell) for cell in row) + ' |')
    return lines


def _plain(value: Any) -> Any:
    """JSON for what json does not know: numpy scalars and arrays, paths."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f'{type(value).__name__} is not JSON serialisable')


def write_results(
    directory: Path, stem: str, lines: Sequence[str], data: Any, echo: bool = True
) -> Path:
    """Write ``<stem>.md`` (the lines) and ``<stem>.json`` (the data) into ``directory``,
    print the Markdown unless ``echo`` is false, and return the Markdown's path."""
    directory.mkdir(parents=True, exist_ok=True)
    markdown = directory / f'{stem}.md'
    markdown.write_text('\n'.join(lines) + '\n')
    (directory / f'{stem}.json').write_text(json.dumps(data, indent=1, default=_plain))
    if echo:
        print('\n'.join(lines), flush=True)
    return markdown


def save_figure(figure: Any, path: Path, dpi: int = 80) -> Path:
    """Save a matplotlib figure as PNG (its directory made) and close it: a bench draws
    dozens, and open figures keep their memory."""
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=dpi)
    plt.close(figure)
    return path
