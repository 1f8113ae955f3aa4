"""The report's page: its sections, tables of a run's figures, and the figures' HTML.

Everything the page needs is in it: plotly.js is inlined once in ``<head>`` (the installed plotly
package's ``package_data/plotly.min.js``, read as a file: the package is never imported), no
stylesheet, font or script is fetched. Each figure is a ``div`` and a ``Plotly.newPlot(id,
data, layout, config)`` call whose arguments are JSON, numpy arrays as plotly.js typed arrays
(``{"dtype": "f4", "bdata": base64, "shape": "N, 2"}``, which plotly.js reads since 2.28; the
package holds 4.1), the layout with plotly's default template
(``package_data/templates/plotly.json``) as the plotly package would write it. Markers let a
headless browser tell a page that drew from one that failed: each figure's ``div`` gets
``data-rendered="yes"`` once plotly has drawn it (and ``data-rect``: its
``left,top,width,height`` on the page, CSS pixels), and every script error or
``console.error`` is appended to the ``data-report-errors`` attribute of ``<html>``.
"""

from __future__ import annotations

import base64
import functools
import html
import importlib.util
import json
import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from operator import attrgetter
from pathlib import Path
from typing import Any

import numpy as np

from fpp_graph.errors import FppError
from fpp_graph.evaluation.report_data import BACKEND_REASON, ReferenceData, RunData, reason_kind

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


# -- plotly.js and the figures ----------------------------------------------------------------
def _plotly_package_file(*parts: str) -> Path:
    """A file of the installed plotly package, found without importing it (``find_spec`` of a
    top-level package runs none of its code)."""
    spec = importlib.util.find_spec("plotly")
    if spec is None or not spec.submodule_search_locations:
        raise FppError("the report needs plotly.js, which the plotly package holds: pip install 'plotly>=6'")
    path = Path(next(iter(spec.submodule_search_locations)), *parts)
    if not path.is_file():
        raise FppError(f"{path} is missing: the plotly package is damaged; reinstall it (pip install --force-reinstall plotly)")
    return path


@functools.cache
def plotly_js() -> bytes:
    """plotly.min.js of the installed plotly package (read once a process)."""
    return _plotly_package_file("package_data", "plotly.min.js").read_bytes()


@functools.cache
def _default_template() -> dict[str, Any]:
    return json.loads(_plotly_package_file("package_data", "templates", "plotly.json").read_text(encoding="utf-8"))


def plotly_template(trace_types: Iterable[str]) -> dict[str, Any]:
    """plotly's default template (the one the plotly package puts into every figure it writes):
    its layout and its defaults of the given trace types."""
    template = _default_template()
    data = template.get("data", {})
    return {"data": {t: data[t] for t in sorted(set(trace_types)) if t in data}, "layout": template.get("layout", {})}


#: numpy dtypes plotly.js reads as typed arrays, and their names there
_TYPED_ARRAY = {"float64": "f8", "float32": "f4", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2", "int32": "i4", "uint32": "u4"}


def typed_array(values: np.ndarray) -> dict[str, str] | list:
    """A numpy array as a plotly.js typed array (``{"dtype", "bdata"[, "shape"]}``, little-endian,
    as the plotly package writes them); 64-bit integers narrowed to the smallest type holding them
    (plotly.js has none of 64 bits); any other array (and an empty one) as a list."""
    array = np.asarray(values)
    if array.size and array.dtype.kind in "iu" and array.dtype.itemsize == 8:
        lo, hi = int(array.min()), int(array.max())
        for kind in ("int8", "int16", "int32") if array.dtype.kind == "i" else ("uint8", "uint16", "uint32"):
            if np.iinfo(kind).min <= lo and hi <= np.iinfo(kind).max:
                array = array.astype(kind)
                break
    name = _TYPED_ARRAY.get(array.dtype.name)
    if name is None or not array.size:
        return _plain(array.tolist())
    little = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
    spec = {"dtype": name, "bdata": base64.b64encode(little.data).decode("ascii")}
    if array.ndim > 1:
        spec["shape"] = ", ".join(str(n) for n in array.shape)
    return spec


def _plain(value: Any) -> Any:
    """``value`` with numpy arrays as typed arrays, numpy scalars as Python ones and NaN or
    infinite floats as null (JSON has neither; the plotly package writes null too)."""
    if isinstance(value, np.ndarray):
        return typed_array(value)
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [v if type(v) is str else _plain(v) for v in value]  # hover texts: thousands of strings, as they are
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _numpy_json(value: Any) -> Any:
    """What :func:`json.dumps` makes of what it does not know: numpy arrays as typed arrays,
    numpy scalars as numbers."""
    if isinstance(value, np.ndarray):
        return typed_array(value)
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON")


def script_json(value: Any) -> str:
    """``value`` as JSON that is safe inside ``<script>``: every ``<`` written ``\\u003c`` (as
    the plotly package writes it), so no ``</script>`` or ``<!--`` (ASCII bytes: one ``memchr``
    pass, 0.1 ms for 0.6 MB where the text's own ``replace`` took 1.7). numpy arrays go in as
    typed arrays (:func:`typed_array`), NaN or infinite numbers outside them as null."""
    try:  # json walks the figure in C, handing over only numpy's objects
        text = json.dumps(value, separators=(",", ":"), allow_nan=False, default=_numpy_json)
    except ValueError:  # a NaN or infinite number: the walk in Python that writes it null
        text = json.dumps(_plain(value), separators=(",", ":"), allow_nan=False)
    return text.encode("ascii").replace(b"<", b"\\u003c").decode("ascii")


def figure_html(figure: Mapping[str, Any], div_id: str) -> str:
    """A figure's ``div`` (its layout's height) and its ``Plotly.newPlot`` call, which marks the
    ``div`` once drawn (plotly.js is the page's: :func:`page`)."""
    layout = dict(figure["layout"])
    layout["template"] = plotly_template(str(t.get("type", "scatter")) for t in figure["data"])
    target = json.dumps(div_id)
    return (f'<div id={target} class="plotly-graph-div" style="height:{int(layout.get("height") or 700)}px; width:100%;"></div>'
            f"<script>if (document.getElementById({target})) {{ Plotly.newPlot({target}, {script_json(figure['data'])}, "
            f"{script_json(layout)}, {script_json(PLOT_CONFIG)}).then(function () {{ {_RENDERED.format(plot_id=div_id)} }}); }}</script>")


def page(title: str, body: Sequence[str], payload: Mapping[str, Any]) -> list[bytes]:
    """The whole page, UTF-8, in parts to write one after the other: plotly.js (the package's
    bytes as they are: 4.8 MB never decoded, encoded or joined), ``body`` parts in order,
    ``payload`` as a JSON block (``#fpp-report-data``, its ``<`` written ``\\u003c``)."""
    head = "\n".join([
        "<!DOCTYPE html>", "<html lang='en'>", "<head>", "<meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>", f"<title>{html.escape(title)}</title>",
        f"<style>{PAGE_STYLE}</style>", f"<script>{ERROR_HOOK}</script>",
        "<script>window.PlotlyConfig = {MathJaxConfig: 'local'};</script>", "<script>",
    ])
    data = json.dumps(payload, default=str, separators=(",", ":")).replace("<", "\\u003c")
    tail = ["</script>", "</head>", "<body>", *body, f"<script type='application/json' id='fpp-report-data'>{data}</script>", "</body>", "</html>"]
    parts = [head.encode("utf-8"), plotly_js()]
    for part in tail:  # each part encoded alone: a figure's ASCII JSON at memcpy speed, whatever the tables hold
        parts += [part.encode("utf-8"), b"\n"]
    return parts


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
    stages: dict[str, Counter] = {}  # in the order of their first candidate
    for (stage, accepted, reason), n in Counter(map(attrgetter("stage", "accepted", "reason"), run.loops)).items():
        counts = stages.setdefault(stage or "—", Counter())
        counts["candidates"] += n
        counts["accepted" if accepted else ("refused by the back-end" if reason == BACKEND_REASON else "refused")] += n
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
