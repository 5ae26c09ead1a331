// The status bar, always on top once logged in: the cell (name, mode), the arm, the sensor, the packing
// line's PackML state when the line is wired, the running job, the queue; STOP (every key, Escape),
// Recover after an arm fault and Resume after a STOP (keys that may recover); the line's unit mode switch
// (keys that may switch it): in Production the line owns the cell and the operator's jobs wait for Manual.

import { api, ApiError, describe } from "../api.js";
import { h, replace } from "../dom.js";

const POLL_MS = 1000;
const POLL_TIMEOUT_MS = 5000; // one poll's bound: a hung service is not waited for
const STALE_MS = 3000; // a status older than this is said to be old, with its age, every second
/** STOP's bound [ms]: the service answers once the job's worker confirmed the stop or was killed
 *  (service.stop_confirm_timeout_s, 2 s by default); past it the page says that it does not know. */
const STOP_TIMEOUT_MS = 10_000;
const STOP_REASON = "STOP on the operator's page";
const QUEUE_RUNS = "The queue runs again."; // a held queue resumed, whoever resumed it
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
  // a hold an operator must resume says since when: it outlives a restart of the service
  const since = queue.held_at ? ` (since ${new Date(queue.held_at).toLocaleString()})` : "";
  $("st-held").textContent = queue.held ? `${queue.held}${since}` : "";
  $("st-held").title = queue.held ?? "";
  $("st-held").hidden = !queue.held;
  const mayRecover = context.can("recover");
  $("recover").hidden = !(mayRecover && arm.faults.length > 0);
  $("resume").hidden = !(mayRecover && queue.held && arm.faults.length === 0);
}

/** A button's call: `button` is disabled while it runs; `name` names it in a failure. */
async function act(button, name, path, body, outcome) {
  button.disabled = true;
  say("");
  try {
    const answer = await api(path, { method: "POST", json: body });
    say(outcome(answer), answer.ok === false ? "bad" : "ok");
    window.dispatchEvent(new Event("cell:changed"));
  } catch (error) {
    say(`${name} failed: ${describe(error)}`, "bad");
  } finally {
    button.disabled = false;
  }
}

const clock = (date) => date.toLocaleTimeString();

/** Say `text` on the bar's outcome line, in the tone of what it tells: "stop" (a STOP, red), "ok" (a
 *  recovery, a resume, a mode switch that went through) or "bad" (a call that failed or did not help). */
function say(text, tone = "stop") {
  $("stop-outcome").textContent = text;
  $("stop-outcome").dataset.tone = tone;
}

/** The outcome of the cell's STOP for people: what the service did, and that the queue is held. */
function stopped(answer) {
  const held = answer.queue_held && !/\bqueue\b/.test(answer.message) ? "; the queue is held until an operator resumes it" : "";
  return `STOP: ${answer.message}${held}.`;
}

/** Why a STOP failed, in words: the cell's answer when it gave one (a refusal is no silence). */
function failure(error) {
  return error instanceof ApiError ? `the cell answered with an error: ${describe(error)}` : describe(error);
}

/** The cell's STOP (the button, Esc): never disabled. While a STOP waits for its answer the button says
 *  so and its outcome counts the seconds; a press meanwhile sends it again (the one before is given up);
 *  no answer within STOP_TIMEOUT_MS, or a failure, is said plainly, apart, and stays until a STOP
 *  succeeds or the operator dismisses it: the arm may still move, whatever the status says since.
 *  Returns {press(), cellAnswers() (the status poll's news after a time without answers), settle() (gives
 *  up a STOP waiting for its answer), dismiss() (clears a failure)}. */
function stopControl() {
  const button = $("stop");
  let pending = null; // {controller, ticker} of the STOP waiting for its answer
  let failed = null; // the failure shown: {text}, and {answersAgain} once the cell answered since
  let heldSaid = null; // the STOP's outcome that says the queue is held: {at [ms], text}, else null

  const settle = () => {
    if (!pending) return;
    pending.controller.abort();
    clearInterval(pending.ticker);
    pending = null;
    button.removeAttribute("aria-busy");
  };

  const showFailure = () => {
    const again = failed.answersAgain
      ? ` The cell answers again since ${clock(failed.answersAgain)}: see the arm's state above, and press STOP again if it must stop.`
      : "";
    $("stop-failed-text").textContent = failed.text + again;
    $("stop-failed").hidden = false;
  };

  const dismiss = () => {
    failed = null;
    $("stop-failed").hidden = true;
    $("stop-failed-text").textContent = "";
  };

  async function press() {
    settle();
    heldSaid = null;
    const sent = new Date();
    const controller = new AbortController();
    const waiting = () => {
      const s = Math.round((Date.now() - sent) / 1000);
      say(`STOP sent at ${clock(sent)}: waiting for the cell's answer${s > 0 ? ` (${s} s)` : ""}…`);
    };
    const mine = { controller, ticker: setInterval(waiting, 1000) };
    pending = mine;
    button.setAttribute("aria-busy", "true");
    waiting();
    try {
      const answer = await api("/api/v1/stop", { method: "POST", json: { reason: STOP_REASON }, timeoutMs: STOP_TIMEOUT_MS, signal: controller.signal });
      if (pending !== mine) return;
      dismiss();
      const text = stopped(answer);
      say(text);
      heldSaid = answer.queue_held ? { at: Date.now(), text } : null;
      window.dispatchEvent(new Event("cell:changed"));
    } catch (error) {
      if (pending !== mine) return; // given up for a newer press
      say("");
      failed = { text: `STOP sent at ${clock(sent)} failed: ${failure(error)}. The arm may still move: press STOP again, or use the cell's emergency stop.` };
      showFailure();
    } finally {
      if (pending === mine) settle();
    }
  }

  function cellAnswers() {
    if (failed === null || failed.answersAgain) return;
    failed.answersAgain = new Date();
    showFailure();
  }

  /** The cell's queue as a status asked for at `askedAt` [ms] says it (`held`: its reason, or null): a
   *  STOP's outcome that says the queue is held is replaced once it runs again, whoever resumed it (the
   *  bar's button, `cell jobs resume`, another page); it said "held" for the rest of the shift. A status
   *  asked for before the STOP's answer came says nothing of the hold, and an outcome said since (a
   *  recovery's, a mode switch's, a failure) is not the STOP's to replace. */
  function queueNow(held, askedAt) {
    if (heldSaid === null || held || askedAt <= heldSaid.at) return;
    const shown = $("stop-outcome").textContent === heldSaid.text;
    heldSaid = null;
    if (shown) say(QUEUE_RUNS, "ok");
  }

  return { press, cellAnswers, settle, dismiss, queueNow };
}

/** Start polling the cell (at once again on a "cell:changed" event: a job ended, a button acted) and wire
 *  the bar's buttons; returns a function that stops both. */
export function startStatus(context) {
  const bar = $("statusbar");
  bar.hidden = false;
  $("whoami").textContent = `${context.who.name} (${context.who.role})`;
  $("logout").title = `Log out ${context.who.name} (${context.who.role})`; // the name is hidden on phones
  let timer = null;
  let alive = true;
  let busy = false;
  let again = false;
  let lastAnswer = Date.now(); // when the status was last updated
  let lastError = "";
  const stopping = stopControl();

  /** Every second: how old the status is, on the bar and to the views ("cell:stale", seconds or null). */
  function age() {
    const ms = Date.now() - lastAnswer;
    const seconds = ms > STALE_MS ? Math.floor(ms / 1000) : null;
    bar.classList.toggle("stale", seconds !== null);
    $("st-link").textContent = seconds === null ? "" : `status not updated for ${seconds} s${lastError ? `: ${lastError}` : ""}`;
    window.dispatchEvent(new CustomEvent("cell:stale", { detail: { seconds } }));
  }
  const ager = setInterval(age, 1000);

  async function poll() {
    if (busy) {
      again = true; // asked for while a poll runs: poll once more right after it
      return;
    }
    busy = true;
    clearTimeout(timer);
    try {
      const askedAt = Date.now();
      const status = await api("/api/v1/cell", { timeoutMs: POLL_TIMEOUT_MS });
      const wasAway = lastError !== "" || Date.now() - lastAnswer > STALE_MS;
      lastAnswer = Date.now();
      lastError = "";
      context.status = status;
      render(status, context);
      stopping.queueNow(status.queue.held, askedAt);
      age();
      if (wasAway) stopping.cellAnswers();
      for (const listener of context.listeners) listener(status);
    } catch (error) {
      lastError = describe(error);
    }
    busy = false;
    if (alive) timer = setTimeout(poll, again ? 0 : POLL_MS);
    again = false;
  }

  /** The page's calls the cell asked to wait ("cell:busy"): said on the bar while there are any. */
  function showBusy(event) {
    const { calls, seconds } = event.detail;
    $("st-busy").hidden = calls === 0;
    if (seconds !== null) {
      $("st-busy").textContent = `cell busy with large answers: asking again in ${seconds} s`;
    }
  }

  const stop = () => stopping.press();
  const recover = () => act($("recover"), "Recover", "/api/v1/arm/recover", undefined,
    (answer) => `Recover: ${answer.message}`);
  const resume = () => act($("resume"), "Resume", "/api/v1/queue/resume", undefined, () => QUEUE_RUNS);
  const switchMode = () => act($("line-mode"), "Line mode switch", "/api/v1/line/mode", { mode: $("line-mode").dataset.mode },
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
  $("stop-dismiss").addEventListener("click", stopping.dismiss, { signal });
  $("recover").addEventListener("click", recover, { signal });
  $("resume").addEventListener("click", resume, { signal });
  $("line-mode").addEventListener("click", switchMode, { signal });
  $("logout").addEventListener("click", logout, { signal });
  document.addEventListener("keydown", onKey, { signal });
  window.addEventListener("cell:changed", poll, { signal });
  window.addEventListener("cell:busy", showBusy, { signal });
  poll();

  return () => {
    alive = false;
    clearTimeout(timer);
    clearInterval(ager);
    stopping.settle();
    stopping.dismiss();
    bar.classList.remove("stale");
    listening.abort();
    say("");
    $("st-link").textContent = "";
    $("st-busy").hidden = true;
    bar.hidden = true;
  };
}
