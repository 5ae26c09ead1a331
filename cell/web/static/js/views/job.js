// A job: while it runs, its progress live from the event stream (curves that grow, the 3D view of the
// growing cloud, the sensor's path and frustum, the ROI box) and a button to stop it; once it ended, its
// result, plots, log and files, and the final cloud with, on packing cells, the packing box.

import { api, ApiError, describe, FILE_TIMEOUT_MS, jobPath, request } from "../api.js";
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
async function trajectory(base) {
  const text = await request(`${base}/files/trajectory.csv`, { timeoutMs: FILE_TIMEOUT_MS });
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
    h("p", { class: "held-note", id: "job-waiting", role: "status" }),
    h("div", { class: "job-actions" }),
    h("p", { class: "outcome", id: "job-stop-outcome", role: "status" }));
}

/** Show job `jobId` (any text of the address) in `main`; returns a function that leaves the view. */
export function showJob(main, context, jobId) {
  let alive = true;
  let ended = false; // the job ended (its result shown or being shown): nothing is polled any more
  let unfollow = () => {};
  let cloudTimer = null;
  let cloudLoad = null; // the cloud's request in flight
  let shownPoints = 0;
  let linkState = "closed";
  let status = null;
  let staleS = null; // seconds without news of the cell (the status bar's poll), null while it answers
  const charts = progressCharts();
  const view = viewSection();
  const path = [];
  const resultSlot = h("div", { id: "result-slot" });
  const head = h("div", {}, h("p", {}, "Loading…"));
  main.append(h("p", {}, h("a", { href: "#/jobs" }, "← All jobs")), head,
    h("div", { class: "live" }, charts.element, view.element), resultSlot);
  view.start();
  charts.element.hidden = true;
  let base = null; // the job's API path; null for an id that names no job (refused below)
  try {
    base = jobPath(jobId);
  } catch {
    // shown where the job would be
  }

  /** The job's cloud into the 3D view; a running job's answer without points (between its snapshot and
   *  its final cloud) leaves the cloud shown as it is. */
  async function loadCloud() {
    try {
      const cloud = await fetchCloud(jobId);
      if (alive && view.view && (cloud.count > 0 || cloud.final || shownPoints === 0)) {
        view.view.setCloud(cloud.positions);
        shownPoints = cloud.count;
      }
    } catch {
      // the next refresh, or the job's end, asks again
    }
  }

  /** loadCloud(), one request at a time: a slow cell is not asked again and again (the request in
   *  flight is what a caller waits for). */
  function refreshCloud() {
    if (!cloudLoad) cloudLoad = loadCloud().finally(() => { cloudLoad = null; });
    return cloudLoad;
  }

  function startCloud() {
    if (cloudTimer === null && !ended) cloudTimer = setInterval(refreshCloud, CLOUD_REFRESH_MS);
  }

  function stopCloud() {
    clearInterval(cloudTimer);
    cloudTimer = null;
  }

  function showLink() {
    const link = document.getElementById("job-link");
    if (!link) return;
    if (ended || ENDED.includes(status)) link.textContent = "";
    else if (staleS !== null && linkState !== "closed") link.textContent = `no news from the cell for ${staleS} s`;
    else link.textContent = LINK_TEXT[linkState];
  }

  /** Why a queued job does not start, when the cell says its queue is held (a STOP, an arm fault, a
   *  dead worker): the job view said only "queued", and a job submitted after a STOP seemed to hang. */
  function showWaiting() {
    const note = document.getElementById("job-waiting");
    if (!note) return;
    const held = status === "queued" ? context.status?.queue?.held : null;
    note.textContent = held ? `Waiting: the queue is held (${held}).` : "";
  }

  function stopButton() {
    const button = h("button", { type: "button", class: "warn", id: "job-stop" });
    button.addEventListener("click", async () => {
      button.disabled = true;
      const outcome = document.getElementById("job-stop-outcome");
      const cancel = status === "queued";
      outcome.textContent = `${cancel ? "Cancelling" : "Stopping"} the job: waiting for the cell's answer…`;
      outcome.dataset.settled = "false";
      try {
        const answer = await api(`${base}/stop`, { method: "POST", json: { reason: `${cancel ? "cancelled" : "stopped"} on the operator's page` } });
        outcome.textContent = answer.message;
        outcome.dataset.settled = "true";
      } catch (error) {
        outcome.textContent = `${cancel ? "Cancel" : "Stop"} failed: ${describe(error)}`;
      } finally {
        button.disabled = false;
      }
    });
    return button;
  }

  function setStatus(now, termination) {
    const badge = document.getElementById("job-status");
    if (!badge) return;
    status = now;
    badge.textContent = status;
    badge.className = `status status-${status}`;
    document.getElementById("job-termination").textContent = termination ?? "";
    const actions = head.querySelector(".job-actions");
    // every key may stop a running job; a queued one's stop cancels it, which a viewer may not do; a
    // stopping one's worker has taken a stop already
    const stoppable = status === "running" || (status === "queued" && context.can("cancel"));
    if (stoppable && !actions.firstChild) actions.append(stopButton());
    // a queued job's stop cancels it (it never moved the arm): the button says what it will do
    if (stoppable) actions.firstChild.textContent = status === "queued" ? "Cancel this job" : "Stop this job";
    showWaiting();
    if (!stoppable) {
      actions.replaceChildren();
      // a stop that failed or got no answer (the cell was away) says nothing of a job that has ended since
      const outcome = document.getElementById("job-stop-outcome");
      if (outcome.dataset.settled === "false") outcome.textContent = "";
    }
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

  /** The ended job (`known`: its record as the API just gave it): its status, final cloud, path and
   *  result, once; every timer stops. */
  async function onEnded(known = null) {
    if (ended) return;
    ended = true;
    stopCloud();
    unfollow();
    showLink();
    window.dispatchEvent(new Event("cell:changed"));
    const job = known ?? await api(base);
    if (!alive) return;
    setStatus(job.status, job.termination);
    const result = job.result ?? {};
    await cloudLoad; // a running job's snapshot asked for before its end is not drawn over the final cloud
    await refreshCloud();
    let moved = path.length > 0;
    if (view.view && !moved) {
      const { path: recorded, pose } = await trajectory(base).catch(() => ({ path: [], pose: null }));
      view.view.setPath(recorded);
      if (pose) view.view.setSensor(...pose);
      moved = recorded.length > 0;
    }
    // from the job's record, not from what loaded: a cloud or path the cell could not send now (busy, the
    // network) is no proof that the job recorded none, and the view would be gone until a reload
    const recordedNothing = !job.started_at || (!(result.n_captures > 0) && !(result.path_length_m > 0));
    if (view.view && recordedNothing && shownPoints === 0 && !moved && !result.packing?.dims_m) {
      view.nothingToDraw(job.status === "cancelled"
        ? "Nothing to draw: the job was cancelled before it started."
        : "Nothing to draw: the job captured no point and recorded no path.");
    }
    const roi = result.perception?.roi;
    if (view.view && roi) view.view.setRoi([roi.aabb_min_m, roi.aabb_max_m]);
    view.showPacking(result.packing);
    if (view.view) view.view.resetView();
    const sections = await resultSections(job).catch((error) => h("p", { class: "error" }, describe(error)));
    if (alive) replace(resultSlot, sections);
    main.querySelector(".live").dataset.ended = "true";
  }
  const showEnded = (known) => onEnded(known).catch((error) => replace(resultSlot, h("p", { class: "error" }, describe(error))));

  /** Whether the job has ended by the REST API's word (asked when its event stream broke or ended
   *  before its result); if so, it is shown. */
  async function endedMeanwhile() {
    const job = await api(base);
    if (!ENDED.includes(job.status)) return false;
    if (alive) showEnded(job);
    return true;
  }

  const onStale = (event) => {
    staleS = event.detail.seconds;
    showLink();
  };
  window.addEventListener("cell:stale", onStale);
  const unlisten = context.onStatus(showWaiting); // the queue held or resumed meanwhile

  (base === null ? Promise.reject(new ApiError(404, `no job ${jobId}`)) : api(base)).then((job) => {
    if (!alive) return;
    replace(head, header(job));
    setStatus(job.status, job.termination);
    if (job.status === "running" || job.status === "stopping") { // its worker runs till it writes its end
      refreshCloud();
      startCloud();
    }
    unfollow = followJob(jobId, {
      onEvent(event) {
        if (!alive) return;
        if (event.event === "state") {
          setStatus(event.data.status, event.data.termination);
          if (event.data.status === "running") startCloud();
        } else if (event.event === "progress") {
          onProgress(event.data);
        } else if (event.event === "result") {
          showEnded();
        }
      },
      onLink(state) {
        linkState = state;
        showLink();
      },
      ended: endedMeanwhile,
    });
  }).catch((error) => replace(head, h("p", { class: "error", role: "alert" }, `Job ${jobId}: ${describe(error)}`)));

  return () => {
    alive = false;
    unfollow();
    stopCloud();
    window.removeEventListener("cell:stale", onStale);
    unlisten();
    view.dispose();
  };
}
