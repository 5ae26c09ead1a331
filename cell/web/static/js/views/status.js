// The status bar, always on top once logged in: the cell (name, mode), the arm, the sensor, the packing
// line's PackML state when the line is wired, the running job, the queue; STOP (every key, Escape),
// Recover after an arm fault and Resume after a STOP (keys that may recover); the line's unit mode switch
// (keys that may switch it): in Production the line owns the cell and the operator's jobs wait for Manual.

import { api, describe } from "../api.js";
import { h, replace } from "../dom.js";

const POLL_MS = 1000;
const STOP_REASON = "STOP on the operator's page";
const ARM_TONE = {
  idle: "ok", moving: "busy", "protective stop": "bad", "emergency stop": "bad", fault: "bad", disconnected: "bad",
};

const $ = (id) => document.getElementById(id);

// The unit mode the switch offers from each mode the line is in (cell.line.packml.OFFERED_MODES).
const OTHER_MODE = { Production: "Manual", Manual: "Production" };

function line(status, context) {
  const wired = status.line;
  $("st-line-item").hidden = !wired;
  if (wired) {
    $("st-line").textContent = `${wired.state_name ?? "?"} (${wired.state ?? "?"})`;
    $("st-line-mode").textContent = wired.mode_name ?? wired.mode ?? "";
    const other = OTHER_MODE[wired.mode_name];
    $("line-mode").hidden = !(other && context.can("mode"));
    $("line-mode").textContent = other ? `Switch to ${other}` : "";
    $("line-mode").dataset.mode = other ? other.toLowerCase() : "";
  }
}

function render(status, context) {
  $("st-name").textContent = status.name;
  $("st-mode").textContent = status.mode;
  const arm = status.arm;
  const other = arm.faults.filter((fault) => fault !== arm.state);
  $("st-arm").textContent = other.length ? `${arm.state}: ${other.join(", ")}` : arm.state;
  $("st-arm").dataset.tone = ARM_TONE[arm.state] ?? "busy";
  $("st-sensor").textContent = `${status.sensor.type}, ${status.sensor.connected ? "ready" : "not connected"}`;
  $("st-sensor").dataset.tone = status.sensor.connected ? "ok" : "idle";
  line(status, context);
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
    window.dispatchEvent(new Event("cell:changed"));
  } catch (error) {
    $("stop-outcome").textContent = `${button.textContent.trim()} failed: ${describe(error)}`;
  } finally {
    button.disabled = false;
  }
}

/** Start polling the cell (at once again on a "cell:changed" event: a job ended, a button acted) and wire
 *  the bar's buttons; returns a function that stops both. */
export function startStatus(context) {
  const bar = $("statusbar");
  bar.hidden = false;
  $("whoami").textContent = `${context.who.name} (${context.who.role})`;
  let timer = null;
  let alive = true;
  let busy = false;
  let again = false;

  async function poll() {
    if (busy) {
      again = true; // asked for while a poll runs: poll once more right after it
      return;
    }
    busy = true;
    clearTimeout(timer);
    try {
      const status = await api("/api/v1/cell");
      context.status = status;
      render(status, context);
      $("st-link").textContent = "";
      for (const listener of context.listeners) listener(status);
    } catch (error) {
      $("st-link").textContent = `status not updated: ${describe(error)}`;
    }
    busy = false;
    if (alive) timer = setTimeout(poll, again ? 0 : POLL_MS);
    again = false;
  }

  const stop = () => act($("stop"), "/api/v1/stop", { reason: STOP_REASON }, (answer) =>
    `STOP: ${answer.message}${answer.queue_held ? ". The queue is held until an operator resumes it." : ""}`);
  const recover = () => act($("recover"), "/api/v1/arm/recover", undefined,
    (answer) => `Recover: ${answer.message}`);
  const resume = () => act($("resume"), "/api/v1/queue/resume", undefined, () => "The queue runs again.");
  const switchMode = () => act($("line-mode"), "/api/v1/line/mode", { mode: $("line-mode").dataset.mode },
    (answer) => `Line: ${answer.message}`);
  const logout = () => context.logout("");
  const onKey = (event) => {
    if (event.key === "Escape" && !event.repeat) {
      event.preventDefault();
      stop();
    }
  };
  const listening = new AbortController(); // removes every listener below at once
  const { signal } = listening;
  $("stop").addEventListener("click", stop, { signal });
  $("recover").addEventListener("click", recover, { signal });
  $("resume").addEventListener("click", resume, { signal });
  $("line-mode").addEventListener("click", switchMode, { signal });
  $("logout").addEventListener("click", logout, { signal });
  document.addEventListener("keydown", onKey, { signal });
  window.addEventListener("cell:changed", poll, { signal });
  poll();

  return () => {
    alive = false;
    clearTimeout(timer);
    listening.abort();
    $("stop-outcome").textContent = "";
    bar.hidden = true;
  };
}
