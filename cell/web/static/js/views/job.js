// A job: while it runs, its progress live from the event stream (curves that grow, the 3D view of the
// growing cloud, the sensor's path and frustum, the ROI box) and a button to stop it; once it ended, its
// result, plots, log and files, and the final cloud with, on packing cells, the packing box.

import { api, describe, request } from "../api.js";
import { fmt, h, replace, when } from "../dom.js";
import { fetchCloud } from "../cloud.js";
import { followJob } from "../sse.js";
import { progressCharts } from "./charts.js";
import { resultSections } from "./result.js";
import { viewSection } from "./view3d.js";

const ENDED = ["completed", "no_object", "failed", "stopped", "cancelled", "interrupted"];
const CLOUD_REFRESH_MS = 1500;
const MAX_PATH_POINTS = 4000;
const LINK_TEXT = { open: "live", reconnecting: "connection lost: reconnecting…", closed: "" };

/** The sensor's path from trajectory.csv (t,x,y,z,qx,qy,qz,qw), at most MAX_PATH_POINTS rows, and the
 *  last pose; for an ended job whose progress this service did not see. */
async function trajectory(jobId) {
  const text = await (await request(`/api/v1/jobs/${jobId}/files/trajectory.csv`)).text();
  const rows = text.trim().split("\n").slice(1).map((line) => line.split(",").map(Number));
  const step = Math.max(1, Math.ceil(rows.length / MAX_PATH_POINTS));
  const path = rows.filter((_, i) => i % step === 0 || i === rows.length - 1).map((r) => r.slice(1, 4));
  const last = rows[rows.length - 1];
  return { path, pose: last ? [last.slice(1, 4), last.slice(4, 8)] : null };
}

function header(job) {
  return h("section", { class: "card job-head", "aria-labelledby": "job-title" },
    h("h1", { id: "job-title" }, "Job ", h("span", { class: "mono" }, job.id)),
    h("p", {}, h("span", { class: `status status-${job.status}`, id: "job-status" }, job.status), " ",
      h("span", { id: "job-link", class: "hint", "aria-live": "polite" }), " ",
      h("span", { id: "job-termination" }, job.termination ?? "")),
    h("dl", { class: "meta" },
      [["Planner", job.planner], ["Object", job.object ?? "–"],
      ["Pose", job.object_pose ? `x ${fmt(job.object_pose[0], 3)} m, y ${fmt(job.object_pose[1], 3)} m, yaw ${fmt(job.object_pose[2], 1)}°` : "–"],
      ["Seed", job.seed], ["Time budget", job.max_time_s === null ? "the cell's" : fmt(job.max_time_s, 0, "s")], ["Part id", job.part_id ?? "–"],
      ["Submitted", `${when(job.created_at)}${job.submitted_by ? ` by ${job.submitted_by}` : ""}`]]
      .map(([name, value]) => h("div", {}, h("dt", {}, name), h("dd", {}, value)))),
    h("div", { class: "job-actions" }),
    h("p", { class: "outcome", id: "job-stop-outcome", role: "status" }));
}

/** Show job `jobId` in `main`; returns a function that leaves the view. */
export function showJob(main, context, jobId) {
  let alive = true;
  let unfollow = () => {};
  let cloudTimer = null;
  const charts = progressCharts();
  const view = viewSection();
  const path = [];
  const resultSlot = h("div", { id: "result-slot" });
  const head = h("div", {}, h("p", {}, "Loading…"));
  main.append(h("p", {}, h("a", { href: "#/jobs" }, "← All jobs")), head,
    h("div", { class: "live" }, charts.element, view.element), resultSlot);
  view.start();
  charts.element.hidden = true;

  async function refreshCloud() {
    try {
      const cloud = await fetchCloud(jobId);
      if (alive && view.view) view.view.setCloud(cloud.positions);
      return cloud;
    } catch {
      return null;
    }
  }

  function stopButton() {
    const button = h("button", { type: "button", class: "warn", id: "job-stop" }, "Stop this job");
    button.addEventListener("click", async () => {
      button.disabled = true;
      try {
        const answer = await api(`/api/v1/jobs/${jobId}/stop`, { method: "POST", json: { reason: "stopped on the operator's page" } });
        document.getElementById("job-stop-outcome").textContent = answer.message;
      } catch (error) {
        document.getElementById("job-stop-outcome").textContent = `Stop failed: ${describe(error)}`;
        button.disabled = false;
      }
    });
    return button;
  }

  function setStatus(status, termination) {
    const badge = document.getElementById("job-status");
    if (!badge) return;
    badge.textContent = status;
    badge.className = `status status-${status}`;
    document.getElementById("job-termination").textContent = termination ?? "";
    const actions = head.querySelector(".job-actions");
    const running = status === "running" || status === "queued";
    if (running && !actions.firstChild) actions.append(stopButton());
    if (!running) actions.replaceChildren();
  }

  function onProgress(progress) {
    charts.element.hidden = false;
    charts.add(progress);
    path.push(progress.sensor_xyz_m);
    if (!view.view) return;
    view.view.setPath(path);
    view.view.setSensor(progress.sensor_xyz_m, progress.sensor_quat_xyzw);
    view.view.setRoi(progress.roi_box_m);
  }

  async function onEnded() {
    clearInterval(cloudTimer);
    window.dispatchEvent(new Event("cell:changed"));
    const job = await api(`/api/v1/jobs/${jobId}`);
    if (!alive) return;
    setStatus(job.status, job.termination);
    const result = job.result ?? {};
    await refreshCloud();
    if (view.view && path.length === 0) {
      const { path: recorded, pose } = await trajectory(jobId).catch(() => ({ path: [], pose: null }));
      view.view.setPath(recorded);
      if (pose) view.view.setSensor(...pose);
    }
    const roi = result.perception?.roi;
    if (view.view && roi) view.view.setRoi([roi.aabb_min_m, roi.aabb_max_m]);
    view.showPacking(result.packing);
    if (view.view) view.view.resetView();
    const sections = await resultSections(job).catch((error) => h("p", { class: "error" }, describe(error)));
    if (alive) replace(resultSlot, sections);
    main.querySelector(".live").dataset.ended = "true";
  }

  api(`/api/v1/jobs/${jobId}`).then((job) => {
    if (!alive) return;
    replace(head, header(job));
    setStatus(job.status, job.termination);
    if (job.status === "running") {
      refreshCloud();
      cloudTimer = setInterval(refreshCloud, CLOUD_REFRESH_MS);
    }
    unfollow = followJob(jobId, {
      onEvent(event) {
        if (!alive) return;
        if (event.event === "state") {
          setStatus(event.data.status, event.data.termination);
          if (event.data.status === "running" && cloudTimer === null) cloudTimer = setInterval(refreshCloud, CLOUD_REFRESH_MS);
        } else if (event.event === "progress") {
          onProgress(event.data);
        } else if (event.event === "result") {
          onEnded().catch((error) => replace(resultSlot, h("p", { class: "error" }, describe(error))));
        }
      },
      onLink(state) {
        const link = document.getElementById("job-link");
        if (link) link.textContent = ENDED.includes(document.getElementById("job-status")?.textContent) ? "" : LINK_TEXT[state];
      },
    });
  }).catch((error) => replace(head, h("p", { class: "error", role: "alert" }, `Job ${jobId}: ${describe(error)}`)));

  return () => {
    alive = false;
    unfollow();
    clearInterval(cloudTimer);
    view.dispose();
  };
}
