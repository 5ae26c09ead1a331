// The page's only door to the cell: every call to /api/v1 goes through here with the key the operator
// logged in with, as "Authorization: Bearer <key>". The key lives in this tab's sessionStorage only: it is
// never put in a URL, a log line or the page's markup.

const KEY_ITEM = "cell.key";
/** How long a call waits for the cell's answer, body included, by default [ms]: a hung service must not
 *  leave a view waiting for ever (files and uploads give their own, longer, bound). */
export const TIMEOUT_MS = 15_000;
/** The bound for a job's files (a cloud.ply of 100 MB over a slow link) and uploads [ms]. */
export const FILE_TIMEOUT_MS = 300_000;
/** How many times a read (GET, HEAD) is sent when the cell answers 503 with a Retry-After: too many
 *  large answers (job lists, file lists, the line's history, clouds) are waiting for their turn
 *  (cell/api/bulk.py), nothing was done, and the cell says when to ask again. Each wait is the
 *  Retry-After, at most MAX_RETRY_AFTER_S, all within the call's time bound. Nothing else is asked
 *  again: a STOP, or anything that acts, says at once that it was refused. */
export const BUSY_TRIES = 5;
const MAX_RETRY_AFTER_S = 5;
let busyCalls = 0; // calls of this page waiting to ask again, on the status bar ("cell:busy")

/** An answer of the API that is not a success: HTTP status, and FastAPI's `detail` (text or a list of
 *  {loc, msg} for validation errors). */
export class ApiError extends Error {
  constructor(status, detail, busy = false) {
    super(typeof detail === "string" ? detail : `HTTP ${status}`);
    this.status = status;
    this.detail = detail;
    this.busy = busy; // a 503 with a Retry-After: the cell was busy, still so after BUSY_TRIES calls
  }
}

export function storedKey() {
  return sessionStorage.getItem(KEY_ITEM);
}

export function storeKey(key) {
  sessionStorage.setItem(KEY_ITEM, key);
}

export function forgetKey() {
  sessionStorage.removeItem(KEY_ITEM);
}

/** Headers of an authorized request, with `extra` added. */
export function authHeaders(extra = {}, key = storedKey()) {
  return { ...extra, Authorization: `Bearer ${key}` };
}

/** The ApiError of `response`; `busy` when it is a read's 503 still refused after BUSY_TRIES calls. */
async function failure(response, busy = false) {
  let detail = response.statusText || `HTTP ${response.status}`;
  try {
    const body = await response.json();
    if (body && body.detail !== undefined) detail = body.detail;
  } catch {
    // not JSON: keep the status text
  }
  if (response.status === 401) window.dispatchEvent(new CustomEvent("cell:unauthorized"));
  return new ApiError(response.status, detail, busy);
}

/** The seconds a 503 answer says to wait before asking again (its Retry-After, in seconds, at most
 *  MAX_RETRY_AFTER_S), or null for any other answer. */
function retryAfter(response) {
  const seconds = Number(response.headers.get("Retry-After") ?? NaN);
  if (response.status !== 503 || !Number.isFinite(seconds) || seconds < 0) return null;
  return Math.min(seconds, MAX_RETRY_AFTER_S);
}

/** Wait `seconds` (ended early by `signal`), counted on the status bar as a call waiting for a busy cell:
 *  "cell:busy" carries how many calls wait, and the wait of the newest. */
async function waitBusy(seconds, signal) {
  busyCalls += 1;
  window.dispatchEvent(new CustomEvent("cell:busy", { detail: { calls: busyCalls, seconds } }));
  try {
    await new Promise((resolve, reject) => {
      const timer = setTimeout(resolve, seconds * 1000);
      signal.addEventListener("abort", () => {
        clearTimeout(timer);
        reject(signal.reason);
      }, { once: true });
    });
  } finally {
    busyCalls -= 1;
    window.dispatchEvent(new CustomEvent("cell:busy", { detail: { calls: busyCalls, seconds: null } }));
  }
}

/** No answer of the cell within a call's time bound (`seconds`). */
export class NoAnswer extends Error {
  constructor(seconds) {
    super(`no answer within ${seconds} s`);
    this.seconds = seconds;
  }
}

/** Run `read(signal)` (a fetch and the reading of its body) with a time bound of `timeoutMs` over both,
 *  also aborted by `options.signal`; a NoAnswer once the bound is reached. */
async function bounded(read, timeoutMs, signal) {
  const timer = AbortSignal.timeout(timeoutMs);
  try {
    return await read(signal ? AbortSignal.any([signal, timer]) : timer);
  } catch (error) {
    if (timer.aborted && !signal?.aborted) throw new NoAnswer(timeoutMs / 1000);
    throw error;
  }
}

async function fetchChecked(path, options, signal) {
  const { json, form, key, headers = {}, timeoutMs: _, ...rest } = options;
  const init = { ...rest, signal, headers: authHeaders(headers, key ?? storedKey()), cache: "no-store" };
  if (json !== undefined) {
    init.body = JSON.stringify(json);
    init.headers["Content-Type"] = "application/json";
  } else if (form !== undefined) {
    init.body = form;
  }
  const reads = ["GET", "HEAD"].includes((init.method ?? "GET").toUpperCase());
  for (let call = 1; ; call += 1) {
    const response = await fetch(path, init);
    if (response.ok) return response;
    const seconds = retryAfter(response);
    if (seconds === null || !reads) throw await failure(response);
    if (call >= BUSY_TRIES) throw await failure(response, true);
    await response.body?.cancel(); // its text says only that the cell is busy
    await waitBusy(seconds, signal);
  }
}

/** The body of an authorized request as `body(response)` reads it; an ApiError for any status but 2xx
 *  (a 503 with a Retry-After is asked again after it, BUSY_TRIES calls in all), a NoAnswer when the
 *  answer, its body included, takes longer than `options.timeoutMs` (TIMEOUT_MS).
 *  `options.json` is sent as a JSON body, `options.form` as multipart form data, `options.signal` aborts
 *  it. A 401 also fires "cell:unauthorized". */
export async function request(path, options = {}, body = (response) => response.text()) {
  return bounded(async (signal) => body(await fetchChecked(path, options, signal)),
    options.timeoutMs ?? TIMEOUT_MS, options.signal);
}

/** The JSON answer of an authorized request (null for 204). */
export async function api(path, options = {}) {
  return request(path, options, (response) => (response.status === 204 ? null : response.json()));
}

/** A file of the API as a Blob (images and downloads: <img src> and <a href> cannot send the key). */
export async function apiBlob(path, timeoutMs = FILE_TIMEOUT_MS) {
  return request(path, { timeoutMs }, (response) => response.blob());
}

/** Save a file of the API under `name`, fetched with the key and handed to the browser as a blob URL. */
export async function download(path, name) {
  const url = URL.createObjectURL(await apiBlob(path));
  const link = document.createElement("a");
  link.href = url;
  link.download = name;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}

/** The API's path of job `jobId`, which may be any text of the page's address: encoded, and "." or ".."
 *  refused (a URL resolves those to another resource of the API, never to a job). */
export function jobPath(jobId) {
  if (jobId === "." || jobId === "..") throw new ApiError(404, `no job ${jobId}`);
  return `/api/v1/jobs/${encodeURIComponent(jobId)}`;
}

/** A readable sentence for an error of a call. */
export function describe(error) {
  if (error instanceof ApiError) {
    if (Array.isArray(error.detail)) return error.detail.map((d) => d.msg).join("; ");
    if (error.busy) return `the cell is busy, asked ${BUSY_TRIES} times: ${error.message}`;
    return `${error.message} (HTTP ${error.status})`;
  }
  if (error instanceof NoAnswer) return `the cell did not answer within ${error.seconds} s`;
  return `the cell did not answer (${error.message})`;
}
