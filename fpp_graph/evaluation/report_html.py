"""The report's page: its sections, tables of a run's figures, and the figures' plotly HTML.

Everything the page needs is in it: plotly.js is inlined once (``include_plotlyjs=True`` for the
first figure), no stylesheet, font or script is fetched. Markers let a headless browser tell a
page that drew from one that failed: each figure's ``div`` gets ``data-rendered="yes"`` once
plotly has drawn it (and ``data-rect``: its ``left,top,width,height`` on the page, CSS pixels),
and every script error or ``console.error`` is appended to the ``data-report-errors`` attribute
of ``<html>``.
"""

from __future__ import annotations

import html
import json
import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from fpp_graph.evaluation.report_data import BACKEND_REASON, ReferenceData, RunData, reason_kind

if TYPE_CHECKING:
    import plotly.graph_objects as go

PAGE_STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 0 auto; max-width: 1500px; padding: 0 18px 40px; color: #222; }
h1 { font-size: 1.35em; margin: 14px 0 2px; } h2 { font-size: 1.15em; margin: 26px 0 6px; border-bottom: 1px solid #ddd; }
h3 { font-size: 1em; margin: 14px 0 4px; } p.caption, p.sub { color: #555; margin: 2px 0 6px; font-size: 0.92em; }
table { border-collapse: collapse; font-size: 0.9em; margin: 4px 0 10px; }
td, th { border: 1px solid #ddd; padding: 2px 8px; text-align: left; vertical-align: top; }
td.n { text-align: right; font-variant-numeric: tabular-nums; } th { background: #f3f3f3; }
.tables { display: flex; flex-wrap: wrap; gap: 0 28px; align-items: flex-start; }
.figure { border: 1px solid #ddd; } ul.notes li { color: #8a5a00; } details summary { cursor: pointer; color: #1f5fbf; }
"""

# before plotly.js: errors of any later script are caught too
ERROR_HOOK = """
(function () {
  var seen = [];
  function note(text) { seen.push(String(text)); document.documentElement.setAttribute("data-report-errors", seen.join(" | ")); }
  window.addEventListener("error", function (e) { note(e.message || e); });
  window.addEventListener("unhandledrejection", function (e) { note(e.reason); });
  var original = console.error;
  console.error = function () { note(Array.prototype.join.call(arguments, " ")); return original.apply(console, arguments); };
})();
"""

# run once plotly has drawn a figure: the marker, and where the figure lies on the page
_RENDERED = ("var d = document.getElementById('{plot_id}'), r = d.getBoundingClientRect(); d.setAttribute('data-rendered', 'yes'); "
             "d.setAttribute('data-rect', [r.left + window.scrollX, r.top + window.scrollY, r.width, r.height].map(Math.round).join(','));")

PLOT_CONFIG = {"displaylogo": False, "responsive": True, "scrollZoom": True}


def shown(value: Any) -> str:
    """A figure as a table shows it: 4 significant digits, thousands grouped, None as a dash."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:,.0f}" if abs(value) >= 1e5 else f"{value:.4g}"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, (list, tuple)):
        return ", ".join(shown(v) for v in value) if len(value) <= 12 else f"{len(value)} values"
    if isinstance(value, dict):
        return json.dumps(value, default=str)[:300]
    return str(value)


def table(rows: Iterable[Sequence[Any]], header: Sequence[str] | None = None, caption: str | None = None) -> str:
    """An HTML table; numbers right-aligned."""
    out = ["<table>"]
    if caption:
        out.append(f"<caption style='text-align:left;font-weight:600'>{html.escape(caption)}</caption>")
    if header:
        out.append("<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
    for row in rows:
        cells = []
        for value in row:
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            cells.append(f"<td class='n'>{html.escape(shown(value))}</td>" if number else f"<td>{html.escape(shown(value))}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "".join(out)


def figure_html(fig: go.Figure, div_id: str, include_plotlyjs: bool) -> str:
    """A figure's ``div`` and its ``Plotly.newPlot`` call (plotly.js inlined with the first one)."""
    import plotly.io as pio

    return pio.to_html(
        fig, include_plotlyjs=include_plotlyjs, full_html=False, div_id=div_id, config=PLOT_CONFIG,
        default_height=f"{fig.layout.height or 700}px", validate=False,
        post_script=_RENDERED,
    )


def page(title: str, body: Sequence[str], payload: Mapping[str, Any]) -> str:
    """The whole page: ``body`` parts in order, ``payload`` as a JSON block (``#fpp-report-data``)."""
    data = json.dumps(payload, default=str, separators=(",", ":")).replace("</", "<\\/")
    return "\n".join([
        "<!DOCTYPE html>", "<html lang='en'>", "<head>", "<meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>", f"<title>{html.escape(title)}</title>",
        f"<style>{PAGE_STYLE}</style>", f"<script>{ERROR_HOOK}</script>", "</head>", "<body>", *body,
        f"<script type='application/json' id='fpp-report-data'>{data}</script>", "</body>", "</html>", "",
    ])


def section(heading: str, *parts: str, caption: str | None = None) -> str:
    head = f"<h2>{html.escape(heading)}</h2>" + (f"<p class='caption'>{html.escape(caption)}</p>" if caption else "")
    return "<section>" + head + "".join(parts) + "</section>"


# -- tables of the run's figures --------------------------------------------------------------
def summary_rows(run: RunData) -> list[tuple[str, Any]]:
    m, p = run.metrics, run.provenance or {}
    rows: list[tuple[str, Any]] = [("input", p.get("input") or m.get("input")), ("results folder", str(run.results_dir))]
    if run.kind == "sequence":
        rows += [("frames used / in the sequence", f"{m.get('frames', len(run.trajectory))} / {m.get('frames_total', '—')}"),
                 ("keyframes", m.get("keyframes", len(run.keyframe_poses)))]
    else:
        rows += [("poses", m.get("poses", len(run.trajectory))), ("edges", m.get("edges"))]
    rows += [("loops accepted / refused", f"{len(run.accepted_loops)} / {len(run.refused_loops)}"),
             ("run time (s)", m.get("seconds") if run.kind == "sequence" else m.get("total_seconds")),
             ("fpp-graph version", p.get("fpp_graph_version"))]
    return rows


def reference_table(run: RunData, reference: ReferenceData | None) -> str:
    """ATE/RPE: the report's own alignment to the reference, and those metrics.json holds."""
    parts = []
    if reference is not None:
        parts.append(table(list(reference.figures.items()), ("figure", "value"), "against the reference"))
    stored = {k: v for k, v in run.metrics.items() if k.startswith(("ate_", "rpe_", "map_rmse", "map_mean", "map_p95"))}
    if stored:
        parts.append(table(list(stored.items()), ("figure", "value"), "in metrics.json"))
    return "".join(parts)


def loop_tables(run: RunData) -> str:
    """Candidates per stage and their fates, precision and recall (``loop_evaluation``), and the refusals by reason."""
    stages: dict[str, Counter] = {}
    for row in run.loops:
        counts = stages.setdefault(row.stage or "—", Counter())
        counts["candidates"] += 1
        counts["accepted" if row.accepted else ("refused by the back-end" if row.reason == BACKEND_REASON else "refused")] += 1
    columns = ("candidates", "accepted", "refused", "refused by the back-end")
    parts = [table([(stage, *(c[k] for k in columns)) for stage, c in stages.items()], ("stage", *columns), "loop candidates by stage")]
    evaluation = run.metrics.get("loop_evaluation")
    if isinstance(evaluation, Mapping) and isinstance(evaluation.get("stages"), Mapping):
        rows = [(name, s.get("pairs"), s.get("true"), s.get("precision"), s.get("recall")) for name, s in evaluation["stages"].items()]
        caption = (f"against the reference: {evaluation.get('true_loops')} true loops among {evaluation.get('universe_pairs')} keyframe pairs "
                   f"(overlap ≥ {evaluation.get('min_overlap')}); {len(evaluation.get('false_accepted') or [])} false loop(s) accepted")
        parts.append(table(rows, ("stage", "pairs", "true", "precision", "recall"), caption))
    refusals = Counter(reason_kind(r.reason) for r in run.refused_loops)
    if refusals:
        example: dict[str, str] = {}
        for r in run.refused_loops:
            example.setdefault(reason_kind(r.reason), r.reason or "")
        reasons: list[tuple[Any, ...]] = [(kind, n, example[kind][:160]) for kind, n in refusals.most_common()]
        parts.append(table(reasons, ("refused because", "candidates", "for example"), "refusals by reason"))
    return "<div class='tables'>" + "".join(parts) + "</div>"


def time_table(run: RunData) -> str:
    """Wall time by stage with its share, and the CPU the run used."""
    m = run.metrics
    by_stage = m.get("seconds_by_stage")
    if isinstance(by_stage, Mapping) and by_stage:
        total = sum(by_stage.values()) or 1.0
        rows: list[tuple[Any, ...]] = [(stage, seconds, f"{100 * seconds / total:.1f} %") for stage, seconds in by_stage.items()]
        rows.append(("total", m.get("seconds", total), "100 %"))
        parts = [table(rows, ("stage", "seconds", "share"), "wall time by stage")]
    else:
        rows = [(k, m[k]) for k in ("read_seconds", "seconds", "total_seconds") if k in m]
        parts = [table(rows, ("stage", "seconds"), "wall time (read the graph; optimise; both)")] if rows else []
    cpu = [(name, m[k]) for k, name in (("cpu_seconds", "seconds"), ("cpu_utilisation", "of every core over the wall time")) if k in m]
    if cpu:
        parts.append(table(cpu, ("CPU", "value"), "CPU of the run and its workers"))
    return "<div class='tables'>" + "".join(parts) + "</div>"


#: metrics.json keys the other tables show (or that are too long for a table)
_SHOWN_ELSEWHERE = {"seconds_by_stage", "seconds", "cpu_seconds", "cpu_utilisation", "loop_evaluation", "source", "config_set_by_source",
                    "rejected_loops", "removed_loops", "inconsistent_loops", "read_seconds", "total_seconds"}


def figures_table(run: RunData) -> str:
    """Every other figure of metrics.json, nested ones as JSON text."""
    rows = [(key, value) for key, value in run.metrics.items() if key not in _SHOWN_ELSEWHERE]
    return table(rows, ("metrics.json", "value")) if rows else ""


def flat_yaml(text: str) -> dict[str, Any]:
    """``section.key`` -> value of a YAML mapping (libyaml's parser where installed: Python's
    took a quarter of a second of the report for three configurations)."""
    import yaml

    return _flat(yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)) or {})


def _flat(node: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(node, Mapping):
        return {prefix.rstrip("."): node}
    out: dict[str, Any] = {}
    for key, value in node.items():
        out.update(_flat(value, f"{prefix}{key}."))
    return out


def config_tables(run: RunData) -> str:
    """The configuration that made the run: what differs from the packaged defaults, what the
    frame source set, and (folded) every value."""
    if run.config_yaml is None:
        return "<p class='sub'>config.yaml is missing.</p>"
    from fpp_graph.config import Config

    defaults = Config()
    dumped = defaults.model_dump(mode="json")
    default = _flat({name: dumped[name] for name in defaults.section_names()})
    used = flat_yaml(run.config_yaml)
    differences = [(k, used.get(k), default.get(k)) for k in sorted(used.keys() | default.keys()) if used.get(k) != default.get(k)]
    parts = [table(differences, ("key", "value", "packaged default"), "differs from the packaged defaults") if differences
             else "<p class='sub'>Every value is the packaged default.</p>"]
    by_source = run.metrics.get("config_set_by_source")
    if isinstance(by_source, Mapping) and by_source:
        rows = [(k, c.get("used"), c.get("given"), c.get("set_by_user")) for k, c in by_source.items()]
        parts.append(table(rows, ("key", "used", "given", "set by the user"), "set by the frame source"))
    every = table(list(used.items()), ("key", "value"))
    return "<div class='tables'>" + "".join(parts) + "</div>" + f"<details><summary>every value (config.yaml)</summary>{every}</details>"


def provenance_tables(run: RunData) -> str:
    parts = []
    if run.provenance:
        parts.append(table(list(run.provenance.items()), ("provenance.json", "value")))
    source = run.metrics.get("source")
    if isinstance(source, Mapping):
        parts.append(f"<details><summary>the frame source's description (metrics.json: source)</summary>"
                     f"{table([(k, v) for k, v in source.items()], ('key', 'value'))}</details>")
    return "".join(parts) or "<p class='sub'>provenance.json is missing.</p>"


def notes_list(notes: Sequence[str]) -> str:
    return "<ul class='notes'>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>" if notes else ""
