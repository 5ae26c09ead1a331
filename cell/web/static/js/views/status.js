// The status bar, always on top once logged in: the cell (name, mode), the arm, the sensor, the packing
// line's PackML state when the line is wired, the running job, the queue; STOP (every key, Escape),
// Recover after an arm fault and Resume after a STOP (keys that may recover).

import { api, describe } from "../api.js";
import { h, replace } from "../dom.js";

const POLL_MS = 1000;
const STOP_REASON = "STOP on the operator's page";
const ARM_TONE = {
  idle: "ok", moving: "busy", "protective stop": "bad", "emergency stop": "bad", fault: "bad", disconnected: "bad",
};

const $ = (id) => document.getElementById(id);

function line(status) {
  const wired = status.line;
  $("st-line-item").hidden = !wired;
  if (wired) {
    $("st-line").textContent = `${wired.state_name ?? "?"} (${wired.state ?? "?"})`;
    $("st-line-mode").textContent = wired.mode ?? "";
  }
}

function render(status, context) {
  $("st-name").textContent = status.name;
  $("st-mode").textContent = status.mode;
  const arm = status.arm;
  $("st-arm").textContent = arm.faults.length ? `${arm.state}: ${arm.faults.join(", ")}` : arm.state;
  $("st-arm").dataset.tone = ARM_TONE[arm.state] ?? "busy";
  $("st-sensor").textContent = `${status.sensor.type}, ${status.sensor.connected ? "ready" : "not connected"}`;
  $("st-sensor").dataset.tone = status.sensor.connected ? "ok" : "idle";
  line(status);
  const job = status.job;
  replace($("st-job"), job
    ? h("a", { href: `#/jobs/${job.id}` }, `${job.id} (${job.planner}${job.part_id ? `, part ${job.part_id}` : ""})`)
    : "none");
  const queue = status.queue;
  $("st-queue").textContent = `${queue.length} waiting${queue.held ? ", held" : ""}`;
  $("st-queue").title = queue.held ?? "";
  $("st-queue").dataset.tone = queue.held ? "bad" : "ok";
  $("st-held").textContent = queue.held ?? "";
  $("st-held").hidden = !queue.held;
  const mayRecover = context.can("recover");
  $("recover").hidden = !(mayRecover && arm.faults.length > 0);
  $("resume").hidden = !(mayRecover && queue.held && arm.faults.length === 0);
}

async function act(button, path, body, outcome) {
  button.disabled = true;
  $("stop-outcome").textContent = "";
  try {
    const answer = await api(path, { method: "POST", json: body });
    $("stop-outcome").textContent = outcome(answer);
  } catch (error) {
    $("stop-outcome").textContent = `${button.textContent.trim()} failed: ${describe(error)}`;
  } finally {
    button.disabled = false;
  }
}

/** Start polling the cell and wire the bar's buttons; returns a function that stops both. */
export function startStatus(context) {
  const bar = $("statusbar");
  bar.hidden = false;
  $("whoami").textContent = `${context.who.name} (${context.who.role})`;
  let timer = null;
  let alive = true;

  async function poll() {
    try {
      const status = await api("/api/v1/cell");
      context.status = status;
      render(status, context);
      $("st-link").textContent = "";
      for (const listener of context.listeners) listener(status);
    } catch (error) {
      $("st-link").textContent = `status not updated: ${describe(error)}`;
    }
    if (alive) timer = setTimeout(poll, POLL_MS);
  }

  const stop = () => act($("stop"), "/api/v1/stop", { reason: STOP_REASON }, (answer) =>
    `STOP: ${answer.message}${answer.queue_held ? ". The queue is held until an operator resumes it." : ""}`);
  const recover = () => act($("recover"), "/api/v1/arm/recover", undefined,
    (answer) => `Recover: ${answer.message}`);
  const resume = () => act($("resume"), "/api/v1/queue/resume", undefined, () => "The queue runs again.");
  const logout = () => context.logout("");
  const onKey = (event) => {
    if (event.key === "Escape" && !event.repeat) {
      event.preventDefault();
      stop();
    }
  };
  $("stop").addEventListener("click", stop);
  $("recover").addEventListener("click", recover);
  $("resume").addEventListener("click", resume);
  $("logout").addEventListener("click", logout);
  document.addEventListener("keydown", onKey);
  poll();

  return () => {
    alive = false;
    clearTimeout(timer);
    $("stop").removeEventListener("click", stop);
    $("recover").removeEventListener("click", recover);
    $("resume").removeEventListener("click", resume);
    $("logout").removeEventListener("click", logout);
    document.removeEventListener("keydown", onKey);
    $("stop-outcome").textContent = "";
    bar.hidden = true;
  };
}
