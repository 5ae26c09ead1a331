// The jobs table: newest first, filtered by status, planner and part id, a page at a time (the list
// endpoint's own query parameters, kept in the address so that a filtered page can be bookmarked). While
// it is shown it is read again every REFRESH_MS (and at once when a job ended or a button acted), so
// queued, running and stopping rows follow their jobs.

import { api, describe } from "../api.js";
import { fmt, h, replace, when } from "../dom.js";

const STATUSES = [
  "queued", "running", "stopping", "completed", "no_object", "failed", "stopped", "cancelled", "interrupted",
];
const PAGE = 20;
const REFRESH_MS = 5000;

function go(filters, offset) {
  const query = new URLSearchParams();
  for (const [name, value] of Object.entries(filters)) if (value) query.set(name, value);
  if (offset > 0) query.set("offset", String(offset));
  const text = query.toString();
  window.location.hash = `#/jobs${text ? `?${text}` : ""}`;
}

function row(job) {
  const result = job.result ?? {};
  const coverage = result.metrics?.coverage_pct;
  const dims = result.packing?.dims_m;
  return h("tr", {},
    h("td", {}, when(job.created_at, true)),
    h("td", {}, h("a", { href: `#/jobs/${job.id}`, class: "mono" }, job.id)),
    h("td", {}, h("span", { class: `status status-${job.status}` }, job.status)),
    h("td", {}, job.planner),
    h("td", {}, job.object ?? "–"),
    h("td", { class: "part", title: job.part_id ?? "" }, job.part_id ?? "–"),
    h("td", { class: "num" }, result.n_captures ?? job.progress?.n_captures ?? "–"),
    h("td", { class: "num" }, fmt(coverage, 1, "%")),
    h("td", { class: "dims" }, dims ? `${dims.map((v) => v.toFixed(3)).join(" × ")} m` : "–"),
    h("td", { class: "termination", title: job.termination ?? "" }, job.termination ?? ""));
}

/** Show the table in `main` for the filters in `params`; returns a function that leaves the view. */
export function showJobs(main, context, params) {
  const filters = { status: params.get("status") ?? "", planner: params.get("planner") ?? "", part_id: params.get("part_id") ?? "" };
  const offset = Math.max(0, Number(params.get("offset")) || 0);

  const status = h("select", { id: "filter-status", name: "status" }, h("option", { value: "" }, "any"),
    STATUSES.map((s) => h("option", { value: s, selected: s === filters.status }, s)));
  const planner = h("select", { id: "filter-planner", name: "planner" }, h("option", { value: "" }, "any"));
  // the API matches a part id whole (GET /api/v1/jobs?part_id=): "crate" finds no "crate-17", and an
  // empty table said only "No job matches.", as if the part had never been scanned
  const part = h("input", { id: "filter-part", name: "part_id", type: "search", value: filters.part_id,
    placeholder: "the whole id" });
  const form = h("form", { class: "filters", role: "search", "aria-label": "Filter jobs" },
    h("label", { for: "filter-status" }, "Status"), status,
    h("label", { for: "filter-planner" }, "Planner"), planner,
    h("label", { for: "filter-part" }, "Part id"), part,
    h("button", { type: "submit" }, "Filter"));
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    go({ status: status.value, planner: planner.value, part_id: part.value.trim() }, 0);
  });

  const body = h("tbody", {}, h("tr", {}, h("td", { colspan: 10 }, "Loading…")));
  const pager = h("div", { class: "pager" });
  const note = h("p", { class: "error", id: "jobs-note", role: "status" });
  main.append(h("section", { class: "card", "aria-labelledby": "jobs-title" },
    h("h2", { id: "jobs-title" }, "Jobs"), form, note,
    h("div", { class: "table-wrap" }, h("table", { class: "jobs" },
      h("thead", {}, h("tr", {}, ["Created", "Job", "Status", "Planner", "Object", "Part id", "Captures", "Cloud coverage",
        "Dimensions", "Termination"].map((title) => h("th", { scope: "col", class: `col-${title.toLowerCase().replace(" ", "-")}` }, title)))),
      body)),
    pager));

  let alive = true;
  api("/api/v1/planners").then((planners) => {
    for (const p of planners) planner.append(h("option", { value: p.name, selected: p.name === filters.planner }, p.name));
  }).catch(() => {});

  const query = new URLSearchParams({ limit: String(PAGE), offset: String(offset) });
  for (const [name, value] of Object.entries(filters)) if (value) query.set(name, value);
  let timer = null;
  let loading = false;
  let loaded = false;

  function showPage(page) {
    const none = filters.part_id
      ? `No job matches. A part id is matched whole, not in part: "${filters.part_id}" finds the jobs of exactly that id.`
      : "No job matches.";
    replace(body, page.items.length ? page.items.map(row) : h("tr", {}, h("td", { colspan: 10 }, none)));
    const last = Math.min(page.offset + page.items.length, page.total);
    // past the last page (an old bookmark, jobs purged since): say so, and Newer leads to the last page
    const lastPage = Math.max(0, Math.floor((page.total - 1) / PAGE) * PAGE);
    const newer = Math.max(0, Math.min(offset - PAGE, lastPage));
    const span = !page.total ? "0 jobs"
      : page.items.length ? `${page.offset + 1}–${last} of ${page.total}` : `no job from ${page.offset + 1} on (${page.total} in all)`;
    replace(pager,
      h("button", { type: "button", disabled: offset === 0, onclick: () => go(filters, newer) }, "Newer"),
      h("span", { "aria-live": "polite" }, span),
      h("button", { type: "button", disabled: offset + page.items.length >= page.total || !page.items.length,
        onclick: () => go(filters, offset + PAGE) }, "Older"));
  }

  async function load() {
    if (loading || !alive) return;
    loading = true;
    clearTimeout(timer);
    try {
      const page = await api(`/api/v1/jobs?${query}`);
      if (!alive) return;
      showPage(page);
      loaded = true;
      note.textContent = "";
    } catch (error) {
      if (!alive) return;
      if (loaded) note.textContent = `The table could not be read again: ${describe(error)}`; // rows stay
      else replace(body, h("tr", {}, h("td", { colspan: 10, class: "error" }, describe(error))));
    } finally {
      loading = false;
      if (alive) timer = setTimeout(load, REFRESH_MS);
    }
  }
  load();
  window.addEventListener("cell:changed", load);
  return () => {
    alive = false;
    clearTimeout(timer);
    window.removeEventListener("cell:changed", load);
  };
}
