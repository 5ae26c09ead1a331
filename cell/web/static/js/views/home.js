// The first view: the new-scan form for keys that may submit (a viewer's key is told it may watch and
// stop, nothing more), and the job running now.

import { describe } from "../api.js";
import { h, replace } from "../dom.js";
import { FormLoadError, scanForm } from "./submit.js";

/** Show the view in `main`; returns a function that leaves it. */
export function showHome(main, context) {
  const running = h("p", { id: "running-now" }, "Nothing is running.");
  const side = h("section", { class: "card", "aria-labelledby": "now-title" },
    h("h2", { id: "now-title" }, "Now"), running, h("p", {}, h("a", { href: "#/jobs" }, "All jobs")));
  // the form needs three answers of the API first: until then the slot says so rather than stay blank;
  // when one fails, it says which and why, and offers to try again
  const slot = h("div", { class: "form-slot" });
  main.append(h("div", { class: "home" }, slot, side));

  const loadForm = () => {
    replace(slot, h("section", { class: "card", id: "form-loading", "aria-busy": "true" }, h("h2", {}, "New scan"),
      h("p", {}, "Loading the form…")));
    scanForm({ onSubmitted: (job) => { window.location.hash = `#/jobs/${job.id}`; } })
      .then((form) => replace(slot, form))
      .catch((error) => {
        const retry = h("button", { type: "button", id: "form-retry" }, "Try again");
        retry.addEventListener("click", loadForm);
        replace(slot, h("section", { class: "card", id: "form-failed" }, h("h2", {}, "New scan"),
          h("p", { class: "error", role: "alert" },
            `The form could not load: ${error instanceof FormLoadError ? error.message : describe(error)}.`),
          retry));
      });
  };
  if (context.can("submit")) {
    loadForm();
  } else {
    replace(slot, h("section", { class: "card", id: "no-submit" }, h("h2", {}, "Watching"),
      h("p", {}, `This key (${context.who.role}) may watch the cell and stop it, but not start scans.`)));
  }

  return context.onStatus((status) => {
    const job = status.job;
    replace(running, job
      ? [job.status === "stopping" ? "Stopping: " : "Running: ", h("a", { href: `#/jobs/${job.id}` }, `job ${job.id}`), ` (${job.planner})`]
      : "Nothing is running.");
  });
}
