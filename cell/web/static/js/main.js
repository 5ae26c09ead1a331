// The operator's page: log in with an API key, then the status bar with STOP stays on top while the
// views change with the address's #fragment: #/ (new scan), #/jobs?... (the jobs table), #/jobs/<id> (a
// job, live while it runs). What the key's role may not do is not offered.

import { api, describe, forgetKey, storedKey } from "./api.js";
import { h, replace } from "./dom.js";
import { showHome } from "./views/home.js";
import { showJob } from "./views/job.js";
import { showJobs } from "./views/jobs.js";
import { showLogin } from "./views/login.js";
import { startStatus } from "./views/status.js";

const main = document.getElementById("main");
const nav = document.getElementById("nav");
let context = null;
let leaveView = () => {};

/** What the views share: the key's identity, its permissions, the newest cell status. */
function makeContext(who) {
  return {
    who,
    can: (permission) => who.permissions.includes(permission),
    status: null,
    listeners: new Set(),
    onStatus(listener) {
      this.listeners.add(listener);
      if (this.status) listener(this.status);
      return () => this.listeners.delete(listener);
    },
  };
}

function route() {
  if (!context) return;
  leaveView();
  const [path, query = ""] = (window.location.hash.replace(/^#/, "") || "/").split("?");
  const params = new URLSearchParams(query);
  const job = path.match(/^\/jobs\/([^/]+)$/);
  for (const link of nav.querySelectorAll("a")) {
    const current = link.getAttribute("href") === `#${path}` || (job && link.getAttribute("href") === "#/jobs");
    if (current) link.setAttribute("aria-current", "page");
    else link.removeAttribute("aria-current");
  }
  main.replaceChildren();
  if (job) leaveView = showJob(main, context, decodeURIComponent(job[1]));
  else if (path === "/jobs") leaveView = showJobs(main, context, params);
  else leaveView = showHome(main, context);
}

async function enter(who) {
  context = makeContext(who);
  document.body.classList.add("signed-in");
  nav.hidden = false;
  const stopStatus = startStatus(context);
  context.logout = (message) => {
    stopStatus();
    leaveView();
    leaveView = () => {};
    forgetKey();
    context = null;
    document.body.classList.remove("signed-in");
    nav.hidden = true;
    login(message);
  };
  route();
}

async function login(message = "") {
  const { who } = await showLogin(main, message);
  await enter(who);
}

async function boot() {
  window.addEventListener("hashchange", route);
  window.addEventListener("cell:unauthorized", () => {
    if (context) context.logout("The cell no longer accepts this key (revoked?). Log in again.");
  });
  const key = storedKey();
  if (!key) {
    await login();
    return;
  }
  try {
    await enter(await api("/api/v1/whoami"));
  } catch (error) {
    forgetKey();
    await login(error.status === 401 ? "" : `Could not reach the cell: ${describe(error)}`);
  }
}

boot().catch((error) => replace(main, h("p", { class: "error", role: "alert" }, `The page failed: ${error}`)));
