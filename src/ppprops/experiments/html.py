"""``index.html``: one static page with every table and figure of a report (relative links only,
so the folder can be copied or served as it is). A small script counts the images that loaded
into ``body[data-images-loaded]`` (of ``data-images-total``), which the browser test reads."""

from __future__ import annotations

import html
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .tables import Table

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1400px; color: #222; padding: 0 1em; }
h1 { font-size: 1.5em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; margin-top: 2em; }
table.results { border-collapse: collapse; font-size: .85em; margin: .5em 0; }
table.results th, table.results td { border: 1px solid #ccc; padding: .25em .5em; text-align: right; }
table.results th { background: #f0f0f0; } table.results td:first-child { text-align: left; }
p.note { font-size: .8em; color: #555; margin: .2em 0; }
.figs img { max-width: 100%; border: 1px solid #ddd; margin: .5em 0; }
.warn { color: #a40; }
"""

_SCRIPT = """
<script>
function countImages() {
  const imgs = Array.from(document.images);
  const ok = imgs.filter(i => i.complete && i.naturalWidth > 0).length;
  document.body.setAttribute('data-images-loaded', String(ok));
  document.body.setAttribute('data-images-total', String(imgs.length));
}
window.addEventListener('load', countImages);
</script>
"""


def _figures(images: Sequence[Path]) -> str:
    return "\n".join(f"<figure><img src='{html.escape(p.name)}' alt='{html.escape(p.stem)}'>"
                     f"<figcaption>{html.escape(p.name)}</figcaption></figure>" for p in images)  # fmt: skip


def write_index(
    out: Path, *, title: str, summary: dict[str, Any], tables: Sequence[Table], curve_images: Sequence[Path],
    cost_images: Sequence[Path], runs: Sequence[dict[str, Any]],
) -> Path:
    """Write ``out/index.html``; every file it links lies next to it."""
    parts = [f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             f"<style>{_STYLE}</style></head><body>", f"<h1>{html.escape(title)}</h1>",
             f"<p>{summary['runs']} run(s), {summary['done']} finished; created {html.escape(summary['created'])}. "
             "Tables also as Markdown, CSV and LaTeX in this folder; every number per run in runs.csv.</p>"]  # fmt: skip
    if summary["runs"] > summary["done"]:
        parts.append(f"<p class='warn'>{summary['runs'] - summary['done']} run(s) are not finished and are left out of the "
                     "numbers: rerun the grid command to complete them.</p>")  # fmt: skip
    for u in summary.get("unreadable", []):
        parts.append(f"<p class='warn'>unreadable: {html.escape(u)}</p>")
    parts.append("<h2>Tables</h2>")
    parts += [t.html() for t in tables] or ["<p>No finished runs.</p>"]
    if curve_images:
        parts += ["<h2>Reward curves</h2>", "<p class='note'>Mean episodic return of each iteration's candidate over seeds, "
                  "shaded ±1 std; the grey span before 0 is the random warm-up (as Fig. fig:optimization_performance).</p>",
                  f"<div class='figs'>{_figures(curve_images)}</div>"]  # fmt: skip
    if cost_images:
        parts += ["<h2>LLM response time against history and prompt size</h2>",
                  "<p class='note'>Every answered LLM call; ★ marks each history setting's last iteration "
                  "(as Fig. fig:history_cost).</p>", f"<div class='figs'>{_figures(cost_images)}</div>"]  # fmt: skip
    head = ["name", "task", "method", "seed", "status", "best", "final", "candidates", "llm_calls", "mean_latency_s", "final_prompt_chars"]
    fmt = lambda v: "" if v is None else (f"{v:.2f}" if isinstance(v, float) else str(v))  # noqa: E731
    rows = "\n".join("<tr>" + "".join(f"<td>{html.escape(fmt(r.get(k)))}</td>" for k in head) + "</tr>" for r in runs)
    parts += ["<h2>Runs</h2>", "<table class='results' data-table='runs'><thead><tr>"
              + "".join(f"<th>{h}</th>" for h in head) + f"</tr></thead><tbody>{rows}</tbody></table>"]  # fmt: skip
    parts += [_SCRIPT, "</body></html>"]
    path = out / "index.html"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
