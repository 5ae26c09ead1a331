// The live job's curves over job time, as progress comes (visual-servoing paper Fig. 4): captures, the
// sensor's path length, H_ROI (named with its form) and, in sim, the coverage of the object (unregistered).

import { h } from "../dom.js";
import { LinePlot } from "../plot.js";

// the words of each form of H_ROI (planners.vs.objective.entropy), as cell/perception/entropy_form.py has them
const ENTROPY_FORM_WORDS = { paper: "eq. 8", observation_aware: "observation-aware" };

/** H_ROI named with its form `form` (progress's and result.json's `h_roi_entropy`): a job of a release
 *  that did not send it (undefined) reported eq. 8's, `paper`; null, a job that perceived nothing. */
export function hRoiName(form = "paper") {
  return form === null ? "H_ROI" : `H_ROI (${ENTROPY_FORM_WORDS[form] ?? form})`;
}

const CURVES = [
  { key: "n_captures", title: "captures", color: "#1f6fb2", yMin: 0 },
  { key: "path_length_m", title: "path length [m]", color: "#5f3dc4", yMin: 0 },
  { key: "h_roi", title: "H_ROI [nats]", color: "#d9480f", yMin: 0,
    titleOf: (progress) => `${hRoiName(progress.h_roi_entropy)} [nats]` },
  // unregistered: eq. 13 of the cloud as it stands, before the final registration (README)
  { key: "coverage_pct", title: "coverage, unregistered [%]", color: "#2b8a3e", yMin: 0, yMax: 100 },
];

/** The curves' section: `element`, `add(progress)` for each progress event, `count` of those added. */
export function progressCharts() {
  const canvases = CURVES.map((c) => h("canvas", { class: "plot", id: `plot-${c.key}` }));
  const plots = CURVES.map((c, i) => new LinePlot(canvases[i], c));
  const summary = h("p", { class: "hint", id: "progress-summary", "aria-live": "polite" }, "No progress yet.");
  const element = h("section", { class: "card charts", "aria-labelledby": "charts-title" },
    h("h2", { id: "charts-title" }, "Progress"), summary, h("div", { class: "plots" }, canvases));
  const charts = {
    element,
    count: 0,
    add(progress) {
      plots.forEach((plot, i) => {
        if (CURVES[i].titleOf) plot.title = CURVES[i].titleOf(progress);
        plot.add(progress.t_s, progress[CURVES[i].key] ?? null);
      });
      charts.count += 1;
      element.dataset.count = String(charts.count);
      summary.textContent = `${charts.count} updates; job time ${progress.t_s.toFixed(1)} s, `
        + `${progress.n_captures} captures, ${progress.n_cloud_points} cloud points`;
    },
  };
  return charts;
}
