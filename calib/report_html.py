"""The page of a calibration report: its figures beside its JSON summary (``index.html``).

One self-contained HTML file (no script, no network): the figures as ``<img>`` with a caption
each, linked to the PNGs beside it, and the summary JSON (also written as a file) in a panel
that stays in view while the figures scroll.
"""

from __future__ import annotations

import html
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mocaprig.errors import CalibrationError
from mocaprig.json_values import to_jsonable

__all__ = ["index_html", "write_index"]

_STYLE = """
body { font-family: sans-serif; margin: 1em; color: #222; }
main { display: grid; grid-template-columns: minmax(0, 3fr) minmax(18em, 2fr); gap: 1.5em; }
figure { margin: 0 0 1.5em 0; }
figure img { max-width: 100%; border: 1px solid #ccc; }
figcaption { font-size: 0.9em; color: #555; }
aside { position: sticky; top: 0; max-height: 97vh; overflow: auto; }
pre { font-size: 0.8em; background: #f6f6f6; padding: 0.8em; white-space: pre-wrap; }
ul.notes { font-size: 0.9em; }
"""


def index_html(
    *,
    title: str,
    figures: Sequence[tuple[str, str]],
    summary: Mapping[str, Any],
    summary_file: str,
    notes: Sequence[str] = (),
) -> str:
    """The report page as text.

    Args:
        title: Page heading.
        figures: ``(file name relative to the page, caption)`` per figure, in page order.
        summary: The JSON summary shown beside the figures.
        summary_file: Its file name relative to the page (linked).
        notes: Remarks listed under the heading (the calibration's notes).
    """
    esc = html.escape
    body = [f"<h1>{esc(title)}</h1>"]
    if notes:
        body.append('<ul class="notes">')
        body.extend(f"<li>{esc(n)}</li>" for n in notes)
        body.append("</ul>")
    body.append("<main><section>")
    for name, caption in figures:
        src = esc(name, quote=True)
        body.append(
            f'<figure><a href="{src}"><img src="{src}" alt="{esc(caption, quote=True)}"></a>'
            f"<figcaption>{esc(caption)} ({esc(name)})</figcaption></figure>"
        )
    text = json.dumps(to_jsonable(dict(summary)), indent=2)
    link = esc(summary_file, quote=True)
    body.append(
        f'</section><aside><h2>Summary (<a href="{link}">{esc(summary_file)}</a>)</h2>'
        f"<pre>{esc(text, quote=False)}</pre></aside></main>"
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{esc(title)}</title><style>{_STYLE}</style></head>\n<body>\n"
        + "\n".join(body)
        + "\n</body></html>\n"
    )


def write_index(
    out_dir: str | Path,
    *,
    title: str,
    figures: Sequence[tuple[Path, str]],
    summary: Mapping[str, Any],
    summary_name: str = "summary.json",
    notes: Sequence[str] = (),
) -> tuple[Path, Path]:
    """Write ``summary_name`` (the JSON) and ``index.html`` into ``out_dir``; returns both paths.

    Raises:
        CalibrationError: a figure is not in ``out_dir`` (the page links them by name).
    """
    out = Path(out_dir)
    rel = []
    for path, caption in figures:
        if Path(path).parent.resolve() != out.resolve():
            msg = f"report figure {path} is not in the report folder {out}; write it there"
            raise CalibrationError(msg)
        rel.append((Path(path).name, caption))
    summary_path = out / summary_name
    summary_path.write_text(
        json.dumps(to_jsonable(dict(summary)), indent=2) + "\n", encoding="utf-8"
    )
    page = out / "index.html"
    page.write_text(
        index_html(
            title=title, figures=rel, summary=summary, summary_file=summary_name, notes=notes
        ),
        encoding="utf-8",
    )
    return summary_path, page
