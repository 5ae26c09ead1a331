// The new-scan form: planner (with its one-line description), the object and its pose on the table for
// sim and dry-run cells (shipped objects and uploaded meshes, in the units of their file), seed, time
// budget and part id; an uploaded object may be deleted. A number field that does not hold a number is refused next to it before anything
// is sent; the API's validation errors (422) are shown next to the field they name, an upload's errors
// next to the upload.

import { api, ApiError, describe, FILE_TIMEOUT_MS } from "../api.js";
import { h, replace } from "../dom.js";

const VIRTUAL_MODES = ["sim", "dry-run"];
/** The longest part id: cell.line.config.PART_ID_MAX, as REST, OPC UA and the line's I/O take it
 *  (tests/test_web_api.py checks that they agree). */
const PART_ID_MAX = 64;
/** The units a mesh file may be in, and the scale that turns them into metres (the API's `scale`;
 *  cell.jobs.placement.UNIT_SCALES). */
const UNITS = [["metres", 1], ["millimetres", 0.001], ["centimetres", 0.01], ["inches", 0.0254]];

function field(name, label, control, hint = "") {
  control.id = `f-${name}`;
  control.name = name;
  const describedBy = [`err-${name}`, hint ? `hint-${name}` : ""].filter(Boolean).join(" ");
  control.setAttribute("aria-describedby", describedBy);
  return h("div", { class: "field", "data-field": name },
    h("label", { for: control.id }, label), control,
    hint ? h("p", { class: "hint", id: `hint-${name}` }, hint) : null,
    h("p", { class: "field-error", id: `err-${name}` }));
}

function numberInput(attrs) {
  return h("input", { type: "number", step: "any", inputmode: "decimal", ...attrs });
}

function objectLabel(entry) {
  const [x, y, z] = entry.extents_m.map((v) => v.toFixed(3));
  return `${entry.name} (${x} × ${y} × ${z} m${entry.source === "uploaded" ? ", uploaded" : ""})`;
}

/** A call the form needs that failed: `message` says which one, and why. */
export class FormLoadError extends Error {
  constructor(what, path, cause) {
    super(`${what} (GET ${path}): ${describe(cause)}`, { cause });
  }
}

/** The answer of `path`, or a FormLoadError naming it as `what`. */
async function needed(path, what) {
  try {
    return await api(path);
  } catch (error) {
    throw new FormLoadError(what, path, error);
  }
}

/** The form in a section; `onSubmitted(job)` after a job was queued. Throws a FormLoadError when a call
 *  it needs fails. */
export async function scanForm({ onSubmitted }) {
  const [planners, cell, objects] = await Promise.all([
    needed("/api/v1/planners", "the planners"), needed("/api/v1/cell", "the cell's status"),
    needed("/api/v1/objects", "the objects"),
  ]);
  const virtual = VIRTUAL_MODES.includes(cell.mode);

  const planner = h("select", {}, planners.map((p) => h("option", { value: p.name, selected: p.default }, p.name)));
  const description = h("p", { class: "hint", id: "hint-planner", "aria-live": "polite" });
  const describePlanner = () => {
    description.textContent = planners.find((p) => p.name === planner.value)?.description ?? "";
  };
  planner.addEventListener("change", describePlanner);
  describePlanner();

  const object = h("select", {});
  const deleteButton = h("button", { type: "button", id: "delete-object", class: "small", hidden: true }, "Delete this upload");
  let listed = objects;
  // only an uploaded object may be deleted (DELETE /api/v1/objects/{name})
  const offerDelete = () => {
    deleteButton.hidden = listed.find((e) => e.name === object.value)?.source !== "uploaded";
  };
  /** The object list with `selected` chosen; by default the object `cell scan` takes when none is named,
   *  as the API marks it (else the browser's choice, the first). */
  const fillObjects = (entries, selected = entries.find((e) => e.default)?.name) => {
    listed = entries;
    replace(object, entries.map((e) => h("option", { value: e.name, selected: e.name === selected }, objectLabel(e))));
    offerDelete();
  };
  object.addEventListener("change", offerDelete);
  fillObjects(objects);
  const label = h("input", { type: "text", maxlength: 128, placeholder: "optional" });
  const x = numberInput({ value: "0", "aria-label": "x [m]" });
  const y = numberInput({ value: "0", "aria-label": "y [m]" });
  const yaw = numberInput({ value: "0", "aria-label": "yaw [deg]" });
  const seed = h("input", { type: "number", min: 0, step: 1, value: "0" });
  const budget = numberInput({ min: 0, class: "budget", placeholder: `${cell.max_time_s} (the cell's)` });
  const part = h("input", { type: "text", maxlength: PART_ID_MAX, placeholder: "optional" });
  const upload = h("input", { type: "file", accept: ".ply,.obj,.stl" });
  const units = h("select", {}, UNITS.map(([name, scale]) => h("option", { value: String(scale) }, name)));
  const uploadButton = h("button", { type: "button", id: "upload" }, "Upload mesh");
  const formError = h("p", { class: "error", role: "alert" });
  const submit = h("button", { type: "submit", class: "primary" }, "Start scan");

  const pose = h("div", { class: "field", "data-field": "object_pose" },
    h("span", { class: "label", id: "pose-label" }, "Pose on the table (from the station)"),
    h("div", { class: "pose", role: "group", "aria-labelledby": "pose-label", "aria-describedby": "err-object_pose" },
      h("label", {}, "x [m] ", x), h("label", {}, "y [m] ", y), h("label", {}, "yaw [deg] ", yaw)),
    h("p", { class: "field-error", id: "err-object_pose" }));
  const plannerField = field("planner", "Planner", planner);
  plannerField.querySelector(".field-error").before(description);
  planner.setAttribute("aria-describedby", "hint-planner err-planner");

  const objectField = field("object", "Object", object);
  objectField.querySelector(".field-error").before(deleteButton);

  const form = h("form", { class: "scan-form", novalidate: true },
    plannerField,
    virtual
      ? [objectField,
        h("div", { class: "field upload" }, field("file", "Or upload a mesh (PLY, OBJ or STL, z up)", upload),
          field("scale", "Units in the file", units), uploadButton),
        pose]
      : field("object", "Label of the part (optional)", label),
    h("div", { class: "row" }, field("seed", "Seed", seed),
      field("max_time_s", "Time budget [s]", budget), field("part_id", "Part id", part)),
    submit, formError);

  const clearErrors = () => {
    for (const p of form.querySelectorAll(".field-error")) p.textContent = "";
    for (const c of form.querySelectorAll("[aria-invalid]")) c.removeAttribute("aria-invalid");
    formError.textContent = "";
  };
  /** `error` next to the field it names, else in `fallback` (under the form, or the upload's). */
  const showError = (error, fallback = formError) => {
    if (error instanceof ApiError && Array.isArray(error.detail)) {
      for (const item of error.detail) {
        const name = item.loc?.[1];
        const slot = name ? form.querySelector(`#err-${CSS.escape(String(name))}`) : null;
        if (slot) {
          slot.textContent = [slot.textContent, item.msg].filter(Boolean).join("; ");
          form.querySelector(`[data-field="${CSS.escape(String(name))}"] input, [data-field="${CSS.escape(String(name))}"] select`)
            ?.setAttribute("aria-invalid", "true");
        } else {
          fallback.textContent = [fallback.textContent, item.msg].filter(Boolean).join("; ");
        }
      }
    } else {
      fallback.textContent = describe(error);
    }
  };
  /** The number in `input`, undefined when it is empty; null when it holds something else (a browser
   *  gives "" for "ten" in a number field: `validity.badInput` tells it apart), said in the field's error
   *  slot `name` as `what`. */
  const number = (input, name, what) => {
    const text = input.value.trim();
    if (!input.validity.badInput && (text === "" || Number.isFinite(Number(text)))) return text === "" ? undefined : Number(text);
    const slot = form.querySelector(`#err-${name}`);
    if (!slot.textContent) slot.textContent = what;
    input.setAttribute("aria-invalid", "true");
    return null;
  };

  uploadButton.addEventListener("click", async () => {
    clearErrors();
    const file = upload.files[0];
    if (!file) {
      form.querySelector("#err-file").textContent = "Choose a file first.";
      return;
    }
    const data = new FormData();
    data.append("file", file);
    if (units.value !== "1") data.append("scale", units.value);
    uploadButton.disabled = true;
    try {
      const entry = await api("/api/v1/objects", { method: "POST", form: data, timeoutMs: FILE_TIMEOUT_MS });
      fillObjects(await api("/api/v1/objects"), entry.name);
      upload.value = "";
    } catch (error) {
      showError(error, form.querySelector("#err-file"));
    } finally {
      uploadButton.disabled = false;
    }
  });

  deleteButton.addEventListener("click", async () => {
    clearErrors();
    const name = object.value;
    if (!window.confirm(`Delete the uploaded object ${name}? The jobs that scanned it keep their results.`)) return;
    deleteButton.disabled = true;
    try {
      await api(`/api/v1/objects/${encodeURIComponent(name)}`, { method: "DELETE" });
      fillObjects(await api("/api/v1/objects"));
    } catch (error) {
      showError(error, form.querySelector("#err-object"));
    } finally {
      deleteButton.disabled = false;
    }
  });

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    clearErrors();
    const body = {
      planner: planner.value,
      seed: number(seed, "seed", "Not a number: a seed is a whole number, 0 or more."),
      max_time_s: number(budget, "max_time_s", "Not a number: seconds, or empty for the cell's default."),
    };
    if (part.value.trim()) body.part_id = part.value.trim();
    if (virtual) {
      body.object = object.value;
      body.object_pose = [x, y, yaw].map((input) => number(input, "object_pose", "x, y and yaw are numbers (m, m, deg).") ?? 0);
    } else if (label.value.trim()) {
      body.object = label.value.trim();
    }
    const invalid = form.querySelector("[aria-invalid='true']");
    if (invalid) {
      invalid.focus();
      return;
    }
    submit.disabled = true;
    try {
      onSubmitted(await api("/api/v1/jobs", { method: "POST", json: body }));
    } catch (error) {
      showError(error);
    } finally {
      submit.disabled = false;
    }
  });

  return h("section", { class: "card", "aria-labelledby": "scan-title" }, h("h2", { id: "scan-title" }, "New scan"), form);
}
