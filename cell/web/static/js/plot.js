// Small line plots on a <canvas> that grow as points come (the live job's curves, like the visual-servoing
// paper's Fig. 4): axes with round ticks, one line, the newest value written in the corner. No library.

const MARGIN = { left: 52, right: 12, top: 26, bottom: 30 };
const AXIS = "#5b6470";
const GRID = "#e3e7ec";
const TEXT = "#1d232b";

/** About `count` round tick values covering [lo, hi]. */
export function ticks(lo, hi, count = 5) {
  if (!(hi > lo)) return [lo];
  const raw = (hi - lo) / count;
  const magnitude = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 2.5, 5, 10].map((m) => m * magnitude).find((s) => s >= raw);
  const values = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) values.push(Number(v.toPrecision(12)));
  return values;
}

function format(value) {
  if (value === 0) return "0";
  const size = Math.abs(value);
  if (size >= 1000 || size < 0.01) return value.toExponential(1);
  return String(Number(value.toPrecision(3)));
}

/** One curve y(x) on `canvas`: `title` (with its unit), `color`; `add(x, y)` appends a point (y null
 *  leaves a gap), `clear()` empties it. The canvas keeps its CSS size and is drawn at the screen's pixel
 *  ratio. */
export class LinePlot {
  constructor(canvas, { title, xLabel = "job time [s]", color = "#1f6fb2", yMin = null, yMax = null }) {
    this.canvas = canvas;
    this.title = title;
    this.xLabel = xLabel;
    this.color = color;
    this.yMin = yMin;
    this.yMax = yMax;
    this.xs = [];
    this.ys = [];
    this.pending = false;
    canvas.setAttribute("role", "img");
    this.describe();
    new ResizeObserver(() => this.draw()).observe(canvas);
  }

  add(x, y) {
    this.xs.push(x);
    this.ys.push(y);
    this.schedule();
  }

  clear() {
    this.xs = [];
    this.ys = [];
    this.schedule();
  }

  /** The newest y that is not null, or null. */
  last() {
    for (let i = this.ys.length - 1; i >= 0; i -= 1) if (this.ys[i] !== null) return this.ys[i];
    return null;
  }

  describe() {
    const last = this.last();
    this.canvas.setAttribute("aria-label", `${this.title}: ${last === null ? "no value yet" : format(last)}`
      + ` after ${this.xs.length} updates`);
  }

  schedule() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.draw();
    });
  }

  /** The data's range, with the plot's fixed bounds and some room. */
  range(values, fixedLo, fixedHi) {
    let lo = Math.min(...values);
    let hi = Math.max(...values);
    if (!Number.isFinite(lo)) [lo, hi] = [0, 1];
    if (fixedLo !== null) lo = Math.min(lo, fixedLo);
    if (fixedHi !== null) hi = Math.max(hi, fixedHi);
    if (hi - lo < 1e-12) [lo, hi] = [lo - 0.5, hi + 0.5];
    return [lo, hi];
  }

  draw() {
    const { canvas } = this;
    const ratio = window.devicePixelRatio || 1;
    const width = canvas.clientWidth;
    const height = canvas.clientHeight;
    if (width === 0 || height === 0) return;
    canvas.width = Math.round(width * ratio);
    canvas.height = Math.round(height * ratio);
    const g = canvas.getContext("2d");
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    g.clearRect(0, 0, width, height);
    g.font = "12px DejaVu Sans, Verdana, sans-serif";
    g.fillStyle = TEXT;
    g.textBaseline = "top";
    g.textAlign = "left";
    const last = this.last();
    const value = last === null ? "–" : format(last);
    // a long title (H_ROI named with its form) is narrowed to end before the value, never under it
    const room = width - MARGIN.left - MARGIN.right - g.measureText(value).width - 8;
    g.fillText(this.title, MARGIN.left, 6, Math.max(room, 0));
    g.textAlign = "right";
    g.fillText(value, width - MARGIN.right, 6);

    const plotW = width - MARGIN.left - MARGIN.right;
    const plotH = height - MARGIN.top - MARGIN.bottom;
    const [x0, x1] = this.range(this.xs, 0, null);
    const [y0, y1] = this.range(this.ys.filter((y) => y !== null), this.yMin, this.yMax);
    const px = (x) => MARGIN.left + ((x - x0) / (x1 - x0)) * plotW;
    const py = (y) => MARGIN.top + plotH - ((y - y0) / (y1 - y0)) * plotH;

    g.lineWidth = 1;
    g.strokeStyle = GRID;
    g.fillStyle = AXIS;
    g.textAlign = "right";
    g.textBaseline = "middle";
    for (const y of ticks(y0, y1, Math.max(2, Math.floor(plotH / 28)))) {
      g.beginPath();
      g.moveTo(MARGIN.left, py(y));
      g.lineTo(MARGIN.left + plotW, py(y));
      g.stroke();
      g.fillText(format(y), MARGIN.left - 6, py(y));
    }
    g.textAlign = "center";
    g.textBaseline = "top";
    for (const x of ticks(x0, x1, Math.max(2, Math.floor(plotW / 70)))) {
      g.fillText(format(x), px(x), MARGIN.top + plotH + 4);
    }
    g.fillText(this.xLabel, MARGIN.left + plotW / 2, MARGIN.top + plotH + 16);
    g.strokeStyle = AXIS;
    g.strokeRect(MARGIN.left, MARGIN.top, plotW, plotH);

    g.strokeStyle = this.color;
    g.fillStyle = this.color;
    g.lineWidth = 2;
    g.beginPath();
    let drawing = false;
    this.xs.forEach((x, i) => {
      const y = this.ys[i];
      if (y === null) {
        drawing = false;
      } else if (drawing) {
        g.lineTo(px(x), py(y));
      } else {
        g.moveTo(px(x), py(y));
        drawing = true;
      }
    });
    g.stroke();
    if (this.xs.length === 1 && this.ys[0] !== null) g.fillRect(px(this.xs[0]) - 2, py(this.ys[0]) - 2, 4, 4);
    this.describe();
  }
}
