"""The site's one style sheet and one script, written beside the pages (assets/): nothing is fetched at view
time, so the site works from file:// and from any static host.

The script does three things, each on whatever page has the elements it needs:

- sorting: every ``<button class="sort">`` in a table header sorts its table's rows by the cells of column
  ``data-col`` (``data-sort`` of a cell when it has one, else its text; ``data-type="number"`` compares
  numbers). The first press sorts ascending, the next descending, and so on; ``aria-sort`` on the header says
  which. Rows without a value stay last either way. Enter and Space on a focused header sort (the keydown
  is handled, so a key event dispatched by a script sorts too);
- filtering: the ``<select id="filter-task">`` and ``<select id="filter-partition">`` show, in a table with
  ``data-filter="view"``, the rows whose ``data-task`` and ``data-partition`` equal the selection (one row set
  per view, "" meaning all), and in a table with ``data-filter="subset"`` the rows that fall in it;
- the compare form: two ``<select>`` of entry slugs open ``<a>--<b>.html``.
"""

from __future__ import annotations

CSS = """
:root { color-scheme: light; }
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 20px auto; max-width: 1180px;
       color: #1d1d1f; line-height: 1.45; padding: 0 16px; }
h1 { font-size: 25px; margin: 0 0 4px 0; }
h2 { font-size: 19px; margin-top: 34px; border-bottom: 1px solid #ddd; padding-bottom: 2px; }
h3 { font-size: 15px; margin: 20px 0 6px 0; }
nav.site { font-size: 14px; margin: 0 0 14px 0; padding-bottom: 8px; border-bottom: 1px solid #eee; }
nav.site a { margin-right: 14px; }
.meta, .caption { color: #555; font-size: 13.5px; max-width: 1000px; }
.note { font-size: 13.5px; background: #fff8e6; border-left: 4px solid #e0a800; padding: 6px 10px; max-width: 1000px; }
.filters { display: flex; flex-wrap: wrap; gap: 8px 22px; align-items: center; margin: 10px 0; font-size: 14px;
           position: sticky; top: 0; background: #fff; padding: 6px 0; z-index: 1; }
.filters label { font-weight: 600; margin-right: 6px; }
.filters select, form.compare select { font-size: 14px; padding: 2px 4px; }
.toc { font-size: 13.5px; } .toc a { margin-right: 10px; }
.scroll { overflow-x: auto; max-width: 100%; }
table { border-collapse: collapse; font-size: 13px; margin: 6px 0 10px 0; font-variant-numeric: tabular-nums; }
th, td { padding: 4px 8px; text-align: right; white-space: nowrap; }
th.label, td.label, th[scope=row] { text-align: left; white-space: normal; }
thead th { border-top: 1.5px solid #333; border-bottom: 1.5px solid #333; vertical-align: bottom; }
tbody tr:last-child td, tbody tr:last-child th { border-bottom: 1.5px solid #333; }
tbody tr:nth-child(even) { background: #f6f7f9; }
tr.reported { background: #fff8e6 !important; color: #5b4300; }
.marker { display: block; font-size: 11px; color: #8a6500; font-style: italic; }
.warn { display: block; font-size: 11px; color: #a33; }
.ci { color: #666; font-size: 11.5px; } td .ci.block { display: block; }
button.sort { font: inherit; font-weight: 600; background: none; border: 0; padding: 0; cursor: pointer; color: inherit;
              text-align: inherit; }
button.sort:focus-visible { outline: 2px solid #0b57d0; outline-offset: 2px; }
button.sort::after { content: " \\2195"; color: #999; font-weight: 400; }
th[aria-sort=ascending] button.sort::after { content: " \\25B2"; color: #333; }
th[aria-sort=descending] button.sort::after { content: " \\25BC"; color: #333; }
table.kv td, table.kv th { text-align: left; white-space: normal; vertical-align: top; }
table.kv td { overflow-wrap: anywhere; max-width: 760px; }
figure.strip { margin: 6px 0 16px 0; } figure.strip img { max-width: 100%; height: auto; display: block;
                                                            border: 1px solid #eee; }
figure.strip figcaption { font-size: 13px; color: #444; }
form.compare { display: flex; flex-wrap: wrap; gap: 8px 16px; align-items: center; font-size: 14px; margin: 10px 0; }
form.compare button { font-size: 14px; }
footer { margin-top: 40px; color: #777; font-size: 12px; border-top: 1px solid #eee; padding-top: 8px; }
"""

JS = r"""
(function () {
  "use strict";

  function sortValue(row, col) {
    var cell = row.cells[col];
    if (!cell) { return ""; }
    var v = cell.getAttribute("data-sort");
    return v === null ? cell.textContent.trim() : v;
  }

  function sortTable(button) {
    var th = button.closest("th"), table = button.closest("table");
    var col = Number(button.getAttribute("data-col"));
    var numeric = th.getAttribute("data-type") === "number";
    var dir = th.getAttribute("aria-sort") === "ascending" ? "descending" : "ascending";
    table.querySelectorAll("thead th[aria-sort]").forEach(function (h) { h.setAttribute("aria-sort", "none"); });
    th.setAttribute("aria-sort", dir);
    Array.prototype.forEach.call(table.tBodies, function (body) {
      var rows = Array.prototype.slice.call(body.rows);
      rows.sort(function (r1, r2) {
        var a = sortValue(r1, col), b = sortValue(r2, col);
        var missA = a === "" || (numeric && isNaN(Number(a))), missB = b === "" || (numeric && isNaN(Number(b)));
        if (missA || missB) { return missA === missB ? 0 : (missA ? 1 : -1); }
        var c = numeric ? Number(a) - Number(b) : a.localeCompare(b);
        return dir === "ascending" ? c : -c;
      });
      rows.forEach(function (r) { body.appendChild(r); });
    });
  }

  function selected(id) {
    var el = document.getElementById(id);
    return el ? el.value : "";
  }

  function applyFilters() {
    var task = selected("filter-task"), part = selected("filter-partition");
    document.querySelectorAll("table[data-filter]").forEach(function (table) {
      var exact = table.getAttribute("data-filter") === "view";
      Array.prototype.forEach.call(table.tBodies, function (body) {
        Array.prototype.forEach.call(body.rows, function (row) {
          var t = row.getAttribute("data-task") || "", p = row.getAttribute("data-partition") || "";
          var show = exact ? (t === task && p === part)
                           : ((task === "" || t === task) && (part === "" || p === part));
          row.hidden = !show;
        });
      });
    });
    document.querySelectorAll("[data-filter-label]").forEach(function (el) {
      var words = [];
      if (task) { words.push("task " + task); }
      if (part) { words.push("partition " + part); }
      el.textContent = words.length ? words.join(", ") : "all examples";
    });
  }

  function openComparison(event) {
    event.preventDefault();
    var form = event.target, a = form.elements.a.value, b = form.elements.b.value;
    var say = form.querySelector("[data-compare-message]");
    if (a === b) { if (say) { say.textContent = "Choose two different entries."; } return; }
    window.location.href = a + "--" + b + ".html";
  }

  document.addEventListener("DOMContentLoaded", function () {
    document.querySelectorAll("button.sort").forEach(function (button) {
      button.addEventListener("click", function () { sortTable(button); });
      button.addEventListener("keydown", function (event) {
        if (event.key === "Enter" || event.key === " " || event.key === "Spacebar") {
          event.preventDefault();
          sortTable(button);
        }
      });
    });
    ["filter-task", "filter-partition"].forEach(function (id) {
      var el = document.getElementById(id);
      if (el) { el.addEventListener("change", applyFilters); }
    });
    if (document.getElementById("filter-task") || document.getElementById("filter-partition")) { applyFilters(); }
    var form = document.getElementById("compare-form");
    if (form) { form.addEventListener("submit", openComparison); }
  });
})();
"""

__all__ = ["CSS", "JS"]
