// An ended job's result (result.json): outcome, figures, metrics, packing dimensions and container,
// safety events; its plots (servo.png, path.png), its log, and every file of its folder to download. Files
// are fetched with the key and shown or saved through blob URLs.

import { api, apiBlob, describe, download, FILE_TIMEOUT_MS, jobPath, request } from "../api.js";
import { bytes, fmt, h, replace } from "../dom.js";
import { hRoiName } from "./charts.js";
import { dimensions } from "./view3d.js";

const PLOTS = [
  ["servo.png", "Servo telemetry: error, objective, gradient, H_ROI and coverage over time"],
  ["path.png", "The sensor's path around the object"],
];

function table(id, rows) {
  return h("table", { class: "facts", id },
    h("tbody", {}, rows.filter(([, value]) => value !== undefined).map(([name, value, key]) =>
      h("tr", {}, h("th", { scope: "row" }, name), h("td", { id: key ? `fig-${key}` : null }, value)))));
}

function figures(result) {
  const m = result.metrics ?? {};
  return table("figures", [
    ["Scan time", fmt(result.scan_time_s, 2, "s"), "scan_time"],
    ["Job time", fmt(result.sim_time_s, 2, "s"), "job_time"],
    ["Path length", fmt(result.path_length_m, 3, "m"), "path_length"],
    ["Captures", result.n_captures ?? "–", "captures"],
    ["Cloud points", result.n_cloud_points ?? "–", "cloud_points"],
    ["Cloud coverage (eq. 13)", fmt(m.coverage_pct, 2, "%"), "coverage"],
    ["Chamfer distance", fmt(m.chamfer_mm, 2, "mm"), "chamfer"],
    ["Hausdorff distance", fmt(m.hausdorff_mm, 2, "mm"), "hausdorff"],
    [`${hRoiName(result.perception?.h_roi_entropy)} at the end`, fmt(result.perception?.h_roi, 4, "nats"), "h_roi"],
  ]);
}

/** The box's upper bound, on which the container is chosen; a face no view saw end is unbounded. */
function upperBound(p) {
  return p.dims_upper_m.map((v) => (v === null ? "unbounded" : v.toFixed(3))).join(" × ");
}

function packing(p) {
  if (!p || !p.dims_m) return null;
  const c = p.container ?? {};
  const inner = c.inner_dims_m ? ` (inside ${c.inner_dims_m.map((v) => v.toFixed(3)).join(" × ")} m${c.rotated ? ", turned" : ""})` : "";
  return h("div", {}, h("h3", {}, "Packing"), table("packing", [
    ["Dimensions (l × w × h)", `${dimensions(p)} m`, "dims"],
    ["Upper bound (l × w × h)", p.dims_upper_m ? `${upperBound(p)} m` : undefined, "upper"],
    ["Container", c.name ? `${c.name}${inner}` : "none fits", "container"],
    ["Why", c.reason ?? "–"],
    ["IoU with the true box", fmt(p.iou, 3)],
    ["Surface reconstructed (voxels)", fmt(p.coverage_pct, 1, "%")],
  ]));
}

/** A count of clamps in words, "787 times": result.json's safety.clamps count how often the guard applied
 *  a limit (mostly a command scaled down at a control tick), and "×787" read as a factor, as if a limit
 *  had been exceeded 787-fold. */
const times = (n) => `${n} ${n === 1 ? "time" : "times"}`;

// how the reason of a stop someone asked for begins (drivers/errors.py): not the guard's doing
const ASKED_STOPS = [["operator stop: ", "operator stop"], ["shutdown stop: ", "stop for the service's shutdown"]];

/** A stop of the job's safety record in words: whose it was, when, and why. */
function stopSaid(e) {
  const asked = ASKED_STOPS.find(([prefix]) => e.reason.startsWith(prefix));
  return asked
    ? `${asked[1]} at ${fmt(e.t, 2, "s")}: ${e.reason.slice(asked[0].length)}`
    : `motion stopped by the guard at ${fmt(e.t, 2, "s")}: ${e.reason}`;
}

function safety(s) {
  if (!s) return null;
  const clamps = Object.entries(s.clamps ?? {});
  const events = [
    ...(s.stops ?? []).map(stopSaid),
    ...(s.refusals ?? []).map((e) => `motion refused at ${fmt(e.t, 2, "s")}: ${e.reason}`),
  ];
  return h("div", { id: "safety" }, h("h3", {}, "Safety"),
    h("p", {}, clamps.length
      ? `Limits applied: ${clamps.map(([k, n]) => `${k.replaceAll("_", " ")} ${times(n)}`).join(", ")}.`
      : "No limit was applied."),
    events.length ? h("ul", {}, events.map((e) => h("li", {}, e))) : h("p", {}, "No stop and no refused motion."));
}

async function plots(jobId, names) {
  const shown = PLOTS.filter(([name]) => names.has(name));
  if (!shown.length) return null;
  const figuresShown = await Promise.all(shown.map(async ([name, caption]) => {
    const url = URL.createObjectURL(await apiBlob(`${jobPath(jobId)}/files/${name}`));
    return h("figure", {}, h("img", { src: url, alt: caption, id: `img-${name.replace(".", "-")}` }), h("figcaption", {}, caption));
  }));
  return h("section", { class: "card", "aria-labelledby": "plots-title" }, h("h2", { id: "plots-title" }, "Plots"), figuresShown);
}

function filesTable(jobId, files) {
  return h("section", { class: "card", "aria-labelledby": "files-title" }, h("h2", { id: "files-title" }, `Files (${files.length})`),
    h("div", { class: "table-wrap files" }, h("table", { id: "files" },
      h("thead", {}, h("tr", {}, h("th", { scope: "col" }, "File"), h("th", { scope: "col", class: "num" }, "Size"), h("th", { scope: "col" }, ""))),
      h("tbody", {}, files.map((f) => {
        const name = f.name.split("/").pop();
        return h("tr", {}, h("td", { class: "mono" }, f.name), h("td", { class: "num" }, bytes(f.size_bytes)),
          h("td", {}, h("button", { type: "button", "aria-label": `Download ${f.name}`, onclick: () => download(f.url, name) }, "Download")));
      })))));
}

/** The sections of an ended job (`job` as GET /api/v1/jobs/{id} gives it); resolves to an element. */
export async function resultSections(job) {
  const result = job.result ?? {};
  const files = await api(`${jobPath(job.id)}/files`);
  const names = new Set(files.map((f) => f.name));
  const log = h("pre", { class: "log", id: "job-log", tabindex: 0, "aria-label": "The job's log" }, "Loading…");
  if (names.has("log.txt")) {
    request(`${jobPath(job.id)}/files/log.txt`, { timeoutMs: FILE_TIMEOUT_MS }).then((text) => replace(log, text))
      .catch((error) => replace(log, `The log could not load: ${describe(error)}`));
  } else {
    replace(log, "No log.");
  }
  const outcome = h("section", { class: "card", "aria-labelledby": "result-title", id: "result" },
    h("h2", { id: "result-title" }, "Result"),
    h("p", {}, h("span", { class: `status status-${job.status}` }, job.status), " ",
      h("span", { id: "result-termination" }, job.termination ?? result.termination ?? "")),
    h("div", { class: "result-grid" }, h("div", {}, h("h3", {}, "Figures"), figures(result)), packing(result.packing), safety(result.safety)));
  const plotSection = await plots(job.id, names).catch((error) => h("p", { class: "error" }, `Plots: ${describe(error)}`));
  return h("div", { class: "result" }, outcome, plotSection,
    h("section", { class: "card", "aria-labelledby": "log-title" }, h("h2", { id: "log-title" }, "Log"), log),
    filesTable(job.id, files));
}
