// The 3D view's section: the three.js view (../scene.js) with its buttons and legend, or a message where
// the browser has no WebGL.

import { h, replace } from "../dom.js";
import { COLORS, CellView } from "../scene.js";

function mark(color) {
  const element = h("span", { class: "swatch" });
  element.style.background = `#${color.toString(16).padStart(6, "0")}`;
  return element;
}

/** The dimensions l x w x h [m] of a packing result, for people. */
export function dimensions(packing) {
  return packing.dims_m.map((v) => v.toFixed(3)).join(" × ");
}

/** `{element, view, start(), showPacking(packing), dispose()}`; `view` is null until `start()` (once
 *  the element is in the document: the view takes its size) and stays null without WebGL. */
export function viewSection() {
  const holder = h("div", { class: "view3d", id: "view3d" });
  const packingNote = h("li", { id: "packing-note", hidden: true });
  const buttons = h("div", { class: "view-buttons" });
  const section = {
    view: null,
    element: h("section", { class: "card", "aria-labelledby": "view-title" },
      h("h2", { id: "view-title" }, "3D view"), holder, buttons,
      h("ul", { class: "legend" },
        h("li", {}, mark(0x3b4cc0), mark(0xe8a33d), "cloud, by height"), h("li", {}, mark(COLORS.path), "sensor path"),
        h("li", {}, mark(COLORS.sensor), "sensor now"), h("li", {}, mark(COLORS.roi), "ROI box"), packingNote)),
    start() {
      try {
        section.view = new CellView(holder);
      } catch (error) {
        replace(holder, h("p", { class: "error" }, `No 3D view: this browser has no WebGL (${error.message}).`));
        return;
      }
      const { view } = section;
      replace(buttons,
        h("button", { type: "button", onclick: () => view.resetView() }, "Reset view"),
        h("button", { type: "button", onclick: () => view.zoom(0.8), "aria-label": "Zoom in" }, "+"),
        h("button", { type: "button", onclick: () => view.zoom(1.25), "aria-label": "Zoom out" }, "−"),
        h("span", { class: "hint" }, "Drag to rotate, wheel to zoom, right-drag or arrow keys to pan."));
    },
    /** The packing box of a packing job's result (`result.packing`), drawn and named in the legend. */
    showPacking(packing) {
      if (!packing?.dims_m) return;
      if (section.view) section.view.setPackingBox(packing);
      const container = packing.container?.name ? `, container ${packing.container.name}` : ", no container fits";
      replace(packingNote, mark(COLORS.packing), `packing box ${dimensions(packing)} m${container}`);
      packingNote.hidden = false;
    },
    /** An ended job that captured nothing and moved nowhere: its empty view gives way to `text`. */
    nothingToDraw(text) {
      section.dispose();
      section.view = null;
      replace(section.element, h("h2", { id: "view-title" }, "3D view"), h("p", { class: "hint", id: "view-nothing" }, text));
    },
    dispose() {
      if (section.view) section.view.dispose();
    },
  };
  return section;
}
