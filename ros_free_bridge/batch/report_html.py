"""The browsable report of a ``retarget-check`` batch: static HTML pages that open from disk.

``OUT/index.html`` (one sortable, filterable row per clip) and ``OUT/clips/<clip>/index.html`` (its
figures, video and reports), made from the rows alone, so they can be rebuilt at any time from
``results.jsonl`` (:func:`ros_free_bridge.batch.results.read_results`). Every link is a relative path
inside ``OUT``; nothing is fetched. What the pages show: docs/retarget_check.md.
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path
from urllib.parse import quote

from ros_free_bridge.batch.results import SETTINGS, ClipResult, atomic_write

#: (row key, column head, kind) of the index table; kind "num" sorts numerically.
INDEX_COLUMNS = (
    ("clip", "clip", "text"),
    ("status", "verdict", "text"),
    ("stage", "stage", "text"),
    ("reason", "reason", "text"),
    ("first_failure_s", "fails at (s)", "num"),
    ("frames", "frames", "num"),
    ("duration_s", "length (s)", "num"),
    ("retime", "retime", "num"),
    ("keypoint_error_mm", "kp error (mm)", "num"),
    ("skate_share", "foot skate", "num"),
    ("jerk_ratio", "jerk ratio", "num"),
    ("limit_violations", "limit hits", "num"),
    ("check_reason", "physics check", "text"),
    ("changed", "changed from the person", "text"),
    ("seconds", "took (s)", "num"),
)
#: What the column heads mean (their tooltips).
HINTS = {
    "first_failure_s": "time of the first failure, seconds into the motion file",
    "retime": "how many times slower the clip had to be played (--auto-retime)",
    "keypoint_error_mm": "mean distance of the robot's keypoints from the scaled person's",
    "skate_share": "share of foot-contact frames in which a foot slid",
    "jerk_ratio": "keypoint jerk of the robot over the source motion's",
    "limit_violations": "joint-limit and velocity-limit violations in the retargeted trajectory",
    "check_reason": "the physics check's verdict, also when the retarget stage failed first",
    "changed": "parts the robot plays differently from the person (a jump kept on the ground, a spin on one foot)",
    "seconds": "compute time of the clip (retarget, check, video)",
}

STYLE = """
body{font:14px/1.4 system-ui,sans-serif;margin:1em 1.5em;color:#222}
h1{font-size:1.4em;margin:.2em 0}
table{border-collapse:collapse}
th,td{border-bottom:1px solid #ddd;padding:2px 6px;text-align:left;vertical-align:top}
#clips{font-size:13px}
th{background:#f3f3f3;position:sticky;top:0}
th.sortable{cursor:pointer;user-select:none}
th.asc::after{content:" \\25B2"} th.desc::after{content:" \\25BC"}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.pass{color:#17692d;font-weight:600} .fail{color:#a3161b;font-weight:600} .error{color:#8a5a00;font-weight:600}
.reason{max-width:22em}
.bar{margin:.6em 0 .8em}
.bar input,.bar select{font:inherit;padding:2px 4px;margin-right:.8em}
.muted{color:#777}
.verdict{display:inline-block;padding:2px 10px;border-radius:4px;color:#fff}
.verdict.pass{background:#17692d;color:#fff} .verdict.fail{background:#a3161b;color:#fff}
.verdict.error{background:#8a5a00;color:#fff}
.cols{display:flex;flex-wrap:wrap;gap:2em} .cols>section{flex:1 1 36em;min-width:0}
section img{max-width:100%}
"""

INDEX_SCRIPT = """
(function(){
  var table=document.getElementById('clips'), body=table.tBodies[0];
  var rows=Array.prototype.slice.call(body.rows);
  var heads=Array.prototype.slice.call(table.tHead.rows[0].cells);
  var text=document.getElementById('filter-text'), status=document.getElementById('filter-status');
  var shown=document.getElementById('shown'), sorted='';
  function key(cell,num){var v=cell.getAttribute('data-v');if(v===null)v=cell.textContent;
    if(num){return v===''?null:parseFloat(v);}return v.toLowerCase();}
  function filter(){
    var q=text.value.trim().toLowerCase(), s=status.value, n=0;
    rows.forEach(function(r){
      var ok=(s===''||r.getAttribute('data-status')===s)&&(q===''||r.textContent.toLowerCase().indexOf(q)>=0);
      r.hidden=!ok; if(ok)n++;});
    shown.textContent=n+' of '+rows.length+' clips shown';
  }
  function sortBy(i,asc){
    var th=heads[i], num=th.getAttribute('data-kind')==='num';
    heads.forEach(function(h){h.classList.remove('asc','desc');});
    th.classList.add(asc?'asc':'desc');
    rows.sort(function(a,b){
      var x=key(a.cells[i],num), y=key(b.cells[i],num);
      if(x===null&&y===null)return 0; if(x===null)return 1; if(y===null)return -1;
      return (x<y?-1:x>y?1:0)*(asc?1:-1);});
    rows.forEach(function(r){body.appendChild(r);});
    sorted=(asc?'':'-')+th.getAttribute('data-key');
  }
  // the view lives in the address: index.html#status=fail&q=balance&sort=-first_failure_s
  function save(){
    var parts=[];
    if(status.value)parts.push('status='+encodeURIComponent(status.value));
    if(text.value)parts.push('q='+encodeURIComponent(text.value));
    if(sorted)parts.push('sort='+encodeURIComponent(sorted));
    history.replaceState(null,'',parts.length?'#'+parts.join('&'):location.pathname);
  }
  function load(){
    var p={};
    location.hash.slice(1).split('&').forEach(function(kv){
      if(!kv)return; var i=kv.indexOf('=');
      p[decodeURIComponent(i<0?kv:kv.slice(0,i))]=i<0?'':decodeURIComponent(kv.slice(i+1));});
    if(p.status!==undefined)status.value=p.status;
    if(p.q!==undefined)text.value=p.q;
    if(p.sort){var desc=p.sort.charAt(0)==='-', k=desc?p.sort.slice(1):p.sort;
      heads.forEach(function(h,i){if(h.getAttribute('data-key')===k)sortBy(i,!desc);});}
  }
  heads.forEach(function(th,i){
    th.classList.add('sortable');
    th.addEventListener('click',function(){sortBy(i,!th.classList.contains('asc'));save();});
  });
  text.addEventListener('input',function(){filter();save();});
  status.addEventListener('change',function(){filter();save();});
  load();
  filter();
  document.body.setAttribute('data-ready','1');
})();
"""

CLIP_SCRIPT = """
(function(){
  var v=document.querySelector('video');
  if(v){v.addEventListener('loadedmetadata',function(){v.setAttribute('data-duration',v.duration.toFixed(2));});}
})();
"""


def _e(text) -> str:
    return html.escape("" if text is None else str(text), quote=True)


def _cell(value) -> str:
    if value is None or value == "":
        return ""
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def clip_href(name: str) -> str:
    """The clip page's link from ``OUT/index.html`` (a relative URL, each path part escaped)."""
    return quote(f"clips/{name}/index.html")


def write_html_report(out, results, total: int | None = None) -> Path:
    """Write ``OUT/index.html`` and one page per clip; the index's path. ``results``:
    :class:`ClipResult` objects (or row dicts) in table order;
    ``total``: the clips in the batch, when some have no row yet (an interrupted run)."""
    out = Path(out)
    rows = [r if isinstance(r, ClipResult) else ClipResult.from_row(r) for r in results]
    try:
        settings = json.loads((out / SETTINGS).read_text())
    except (OSError, ValueError):
        settings = {}
    for r in rows:
        folder = out / "clips" / r.clip
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write(folder / "index.html", clip_page(r, folder, settings), sync=False)
    index = out / "index.html"
    atomic_write(index, index_page(rows, settings, total), sync=False)
    return index


def index_page(rows, settings: dict, total: int | None = None) -> str:
    n = len(rows)
    counts = {s: sum(r.status == s for r in rows) for s in ("pass", "fail", "error")}
    title = f"Retarget-and-check: {counts['pass']} of {n} clips pass"
    note = (
        ""
        if total is None or total == n
        else f' <span class="muted">({n} of {total} clips done: '
        "the batch was interrupted; --resume continues it)</span>"
    )
    what = ", ".join(f"{k} {_e(settings[k])}" for k in ("robot", "retargeter") if settings.get(k) is not None)
    heads = "".join(
        f'<th data-key="{key}" data-kind="{kind}" title="{_e(HINTS.get(key, ""))}">{_e(label)}</th>'
        for key, label, kind in INDEX_COLUMNS
    )
    body = []
    for r in rows:
        d = r.row()
        cells = []
        for key, _, kind in INDEX_COLUMNS:
            v = d.get(key)
            if key == "clip":
                extra = f'<br><span class="muted">with actor {_e(r.actor)}</span>' if r.actor else ""
                cells.append(f'<td data-v="{_e(r.clip)}"><a href="{clip_href(r.clip)}">{_e(r.clip)}</a>{extra}</td>')
            elif key == "status":
                cells.append(f'<td class="{_e(v)}" data-v="{_e(v)}">{_e(str(v).upper())}</td>')
            elif kind == "num":
                cells.append(f'<td class="num" data-v="{_e(_cell(v))}">{_e(_cell(v))}</td>')
            else:
                cls = ' class="reason"' if key == "reason" else ""
                cells.append(f"<td{cls}>{_e(v)}</td>")
        body.append(f'<tr data-status="{_e(r.status)}" data-clip="{_e(r.clip)}">{"".join(cells)}</tr>')
    options = "".join(f'<option value="{s}">{s} ({counts[s]})</option>' for s in ("pass", "fail", "error"))
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{_e(title)}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>{STYLE}</style></head>
<body>
<h1>{_e(title)}</h1>
<p>{counts["pass"]} pass, {counts["fail"]} fail, {counts["error"]} error{("; " + what) if what else ""}.{note}
Click a column head to sort, a clip to see its video, plots and reports.
Tables: <a href="results.csv">results.csv</a>, <a href="results.md">results.md</a>.</p>
<div class="bar"><label>verdict <select id="filter-status"><option value="">all ({n})</option>{options}</select></label>
<label>search <input id="filter-text" type="search" placeholder="clip name or reason"></label>
<span id="shown" class="muted"></span></div>
<table id="clips"><thead><tr>{heads}</tr></thead>
<tbody>
{chr(10).join(body)}
</tbody></table>
<script>{INDEX_SCRIPT}</script>
</body></html>
"""


def clip_page(r, folder: Path, settings: dict) -> str:
    depth = len(Path("clips", r.clip).parts)
    up = "../" * depth
    figures = [
        ("verdict", r.status.upper()),
        ("stage", r.stage or "-"),
        ("reason", r.reason or "-"),
        ("first failure (s into the file)", _cell(r.first_failure_s) or "-"),
        ("frames / duration (s)", f"{r.frames} / {_cell(r.duration_s)}"),
        ("retime", _cell(r.retime)),
        ("keypoint error mean (mm)", _cell(r.keypoint_error_mm) or "-"),
        ("foot skate (share of contact frames)", _cell(r.skate_share) or "-"),
        ("jerk ratio (robot / source)", _cell(r.jerk_ratio) or "-"),
        ("limit + velocity violations", _cell(r.limit_violations) or "-"),
        ("physics check", r.check_reason or ("pass" if r.status == "pass" else "-")),
        ("changed from the person (s into the file)", getattr(r, "changed", "") or "-"),
        ("compute (s)", _cell(r.seconds)),
    ]
    if r.actor:
        figures.insert(0, ("actor (the robot plays the other person)", r.actor))
    facts = "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in figures)
    parts = []
    video = folder / "video.mp4"
    if video.is_file():
        what = (
            "the actor | the person the robot plays | the robot with the actor"
            if r.actor
            else "the person (beside) and the robot, as the simulated servos played it"
        )
        parts.append(
            f'<h2>Video</h2><p class="muted">{_e(what)}</p>'
            f'<video src="video.mp4" controls loop muted playsinline preload="metadata"></video>'
        )
    elif (folder / "video_error.txt").is_file():
        parts.append(f'<h2>Video</h2><p class="muted">{_e((folder / "video_error.txt").read_text().strip())}</p>')
    files = [
        f'<a href="{quote(n)}">{_e(n)}</a>'
        for n in ("trajectory.npz", "check.json", "retarget.report.json", "traceback.txt")
        if (folder / n).is_file()
    ]
    if files:
        parts.append(f"<p>Files: {', '.join(files)}</p>")
    sections = []
    for name, title in (("check.md", "Physics check"), ("retarget.report.md", "Retarget report")):
        if (folder / name).is_file():
            body = markdown_to_html((folder / name).read_text(), shift=2)
            sections.append(f"<section><h2>{title}</h2>{body}</section>")
    robot = f" on {_e(settings['robot'])}" if settings.get("robot") else ""
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{_e(r.clip)}: {_e(r.status.upper())}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>{STYLE}</style></head>
<body>
<p><a href="{up}index.html">&larr; all clips</a></p>
<h1>{_e(r.clip)}{robot} <span class="verdict {_e(r.status)}">{_e(r.status.upper())}</span></h1>
<table class="facts">{facts}</table>
{"".join(parts)}
<div class="cols">{"".join(sections)}</div>
<script>{CLIP_SCRIPT}</script>
</body></html>
"""


_IMAGE = re.compile(r"^!\[([^\]]*)\]\(([^)\s]+)\)$")


def _inline(text: str) -> str:
    out = _e(text)
    out = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", out)
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", out)


def markdown_to_html(md: str, shift: int = 0) -> str:
    """The little markdown our reports use (headings, tables, lists, images alone on a line,
    bold, code, paragraphs) as HTML; headings moved ``shift`` levels down."""
    out: list[str] = []
    lines = md.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].rstrip()
        if not line.strip():
            i += 1
            continue
        m = re.match(r"^(#{1,6})\s+(.*)$", line)
        if m:
            level = min(6, len(m.group(1)) + shift)
            out.append(f"<h{level}>{_inline(m.group(2))}</h{level}>")
            i += 1
            continue
        m = _IMAGE.match(line.strip())
        if m:
            out.append(f'<p><img src="{quote(m.group(2))}" alt="{_e(m.group(1))}" loading="lazy"></p>')
            i += 1
            continue
        if line.lstrip().startswith("|"):
            block = []
            while i < len(lines) and lines[i].lstrip().startswith("|"):
                block.append([c.strip() for c in lines[i].strip().strip("|").split("|")])
                i += 1
            head, rows = block[0], [b for b in block[1:] if not all(re.fullmatch(r":?-{3,}:?", c) for c in b)]
            out.append(
                "<table><thead><tr>"
                + "".join(f"<th>{_inline(c)}</th>" for c in head)
                + "</tr></thead><tbody>"
                + "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>" for r in rows)
                + "</tbody></table>"
            )
            continue
        if re.match(r"^\s*[-*]\s+", line):
            items = []
            while i < len(lines) and re.match(r"^\s*[-*]\s+", lines[i]):
                items.append(re.sub(r"^\s*[-*]\s+", "", lines[i]))
                i += 1
            out.append("<ul>" + "".join(f"<li>{_inline(t)}</li>" for t in items) + "</ul>")
            continue
        para = []
        while (
            i < len(lines)
            and lines[i].strip()
            and not re.match(r"^(#{1,6}\s|\||\s*[-*]\s)", lines[i])
            and not _IMAGE.match(lines[i].strip())
        ):
            para.append(lines[i].strip())
            i += 1
        out.append(f"<p>{_inline(' '.join(para))}</p>")
    return "\n".join(out)
