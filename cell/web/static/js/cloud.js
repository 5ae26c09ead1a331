// A job's cloud from GET /api/v1/jobs/{id}/cloud: a 40-byte little-endian header (magic "CLD1", uint32
// points sent, uint32 points in the cloud, uint32 final, float32 box min and max [m]) then uint16 x, y, z
// per point within the box (cell/service/clouds.py).

import { jobPath, request } from "./api.js";

const HEADER_BYTES = 40;
const LEVELS = 65535;

/** Decode an answer into {positions: Float32Array (x, y, z per point, base frame [m]), count, total,
 *  final}. */
export function decodeCloud(buffer) {
  const view = new DataView(buffer);
  const magic = String.fromCharCode(...new Uint8Array(buffer, 0, 4));
  const count = view.getUint32(4, true);
  if (magic !== "CLD1" || buffer.byteLength !== HEADER_BYTES + 6 * count) {
    throw new Error(`not a cloud answer (${magic}, ${buffer.byteLength} bytes)`);
  }
  const total = view.getUint32(8, true);
  const final = view.getUint32(12, true) === 1;
  const lo = [0, 1, 2].map((k) => view.getFloat32(16 + 4 * k, true));
  const hi = [0, 1, 2].map((k) => view.getFloat32(28 + 4 * k, true));
  const scale = lo.map((l, k) => (hi[k] - l) / LEVELS);
  const q = new Uint16Array(buffer, HEADER_BYTES, 3 * count);
  const positions = new Float32Array(3 * count);
  for (let i = 0; i < q.length; i += 1) positions[i] = lo[i % 3] + q[i] * scale[i % 3];
  return { positions, count, total, final };
}

/** The job's cloud now (the final one once it ended), at most `maxPoints` points. */
export async function fetchCloud(jobId, maxPoints = 200000) {
  return decodeCloud(await request(`${jobPath(jobId)}/cloud?max_points=${maxPoints}`, {},
    (response) => response.arrayBuffer()));
}
