// A job's Server-Sent Events, read with fetch() and a stream reader: EventSource cannot send the
// Authorization header. When the stream breaks or ends before the job's final `result` event, the job's
// status is read from the REST API: a job that ended meanwhile (the service restarted under it: it is
// `interrupted`, and the restarted service's event ids begin at 1 again, so Last-Event-ID asks for
// nothing) is handed to the caller and following stops; otherwise it reconnects by itself with
// Last-Event-ID, so the service sends exactly the events after the last one seen: a brief disconnect
// loses no progress. Reconnecting backs off while connections bring no event.

import { authHeaders, jobPath } from "./api.js";

const RETRY_MS = [500, 1000, 2000, 5000];
const SILENCE_MS = 45_000; // the service sends a keep-alive every 15 s: longer silence is a dead link

/** Parse the text of an event stream as it comes (the SSE wire format: `field: value` lines, an empty
 *  line ends an event, `:` starts a comment). `feed(text)` returns the complete events so far. */
export class EventParser {
  constructor() {
    this.buffer = "";
    this.fields = {};
  }

  feed(text) {
    this.buffer += text;
    const lines = this.buffer.split(/\r\n|\r|\n/);
    this.buffer = lines.pop();
    const events = [];
    for (const line of lines) {
      if (line === "") {
        if (this.fields.data !== undefined) {
          events.push({ id: Number(this.fields.id), event: this.fields.event || "message", data: this.fields.data });
        }
        this.fields = {};
      } else if (!line.startsWith(":")) {
        const colon = line.indexOf(":");
        const name = colon < 0 ? line : line.slice(0, colon);
        const value = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
        this.fields[name] = name === "data" && this.fields.data !== undefined ? `${this.fields.data}\n${value}` : value;
      }
    }
    return events;
  }
}

/** Follow the events of job `jobId`: `onEvent({id, event, data})` for each (data parsed from JSON) in
 *  order, each once; `onLink(state)` with "open", "reconnecting" or "closed". `ended()` is asked each time
 *  the stream broke or ended before the `result` event: it resolves true when the job has ended by the
 *  REST API's word (the caller shows it from there) and following stops; false or an error, and the
 *  stream is opened again. Returns a function that stops following. Ends by itself after the `result`
 *  event, on 401/404, or when `ended()` says so. */
export function followJob(jobId, { onEvent, onLink = () => {}, ended = async () => false }) {
  let lastId = 0;
  let stopped = false;
  let controller = null;
  let attempt = 0;

  async function readOnce() {
    controller = new AbortController();
    let silence = setTimeout(() => controller.abort(), SILENCE_MS);
    const headers = authHeaders({ Accept: "text/event-stream" });
    if (lastId > 0) headers["Last-Event-ID"] = String(lastId);
    const response = await fetch(`${jobPath(jobId)}/events`, {
      headers, signal: controller.signal, cache: "no-store",
    });
    if (response.status === 401 || response.status === 404) {
      if (response.status === 401) window.dispatchEvent(new CustomEvent("cell:unauthorized"));
      return true;
    }
    if (!response.ok) throw new Error(`HTTP ${response.status}`);
    onLink("open");
    const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
    const parser = new EventParser();
    try {
      for (;;) {
        const { value, done } = await reader.read();
        if (done) return false;
        clearTimeout(silence);
        silence = setTimeout(() => controller.abort(), SILENCE_MS);
        for (const raw of parser.feed(value)) {
          if (!(raw.id > lastId)) continue;
          lastId = raw.id;
          attempt = 0; // this connection brought news: a break after it is retried after the shortest wait
          const event = { id: raw.id, event: raw.event, data: JSON.parse(raw.data) };
          onEvent(event);
          if (event.event === "result") return true;
        }
      }
    } finally {
      clearTimeout(silence);
      reader.cancel().catch(() => {});
    }
  }

  (async () => {
    while (!stopped) {
      let finished = false;
      try {
        finished = await readOnce();
      } catch {
        finished = false;
      }
      if (finished || stopped) break;
      onLink("reconnecting");
      if (await ended().catch(() => false)) break;
      if (stopped) break;
      await new Promise((resolve) => setTimeout(resolve, RETRY_MS[Math.min(attempt, RETRY_MS.length - 1)]));
      attempt += 1;
    }
    onLink("closed");
  })();

  return () => {
    stopped = true;
    if (controller) controller.abort();
  };
}
