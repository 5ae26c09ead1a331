// The 3D view of a job (three.js), in the robot's base frame [m], z up: the accumulated cloud coloured by
// height, the sensor's path, the sensor's current frustum, the object's ROI box and, on packing cells, the
// packing box. Orbit with the mouse (left: rotate, wheel: zoom, right: pan), or the arrow keys (pan) and
// the view's buttons; "Reset view" frames what is shown. Drawn on demand, not in a loop.

import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";

export const COLORS = {
  background: 0xf4f6f8, grid: 0xc5ccd4, path: 0x1f6fb2, sensor: 0xd9480f, roi: 0x2b8a3e, packing: 0x9c36b5,
};
const FRUSTUM_DEPTH_M = 0.08;
const FRUSTUM_HALF_ANGLE_RAD = (22.5 * Math.PI) / 180; // drawn with a nominal 45 deg field of view
const LOW = new THREE.Color(0x3b4cc0);
const HIGH = new THREE.Color(0xe8a33d);

function boxEdges(color) {
  const edges = new THREE.LineSegments(new THREE.EdgesGeometry(new THREE.BoxGeometry(1, 1, 1)),
    new THREE.LineBasicMaterial({ color }));
  edges.visible = false;
  return edges;
}

function frustum() {
  const d = FRUSTUM_DEPTH_M;
  const s = d * Math.tan(FRUSTUM_HALF_ANGLE_RAD);
  // the sensor frame: z along the optical axis, x right, y down
  const corners = [[-s, -s, d], [s, -s, d], [s, s, d], [-s, s, d]];
  const vertices = [];
  corners.forEach((c, i) => {
    vertices.push(0, 0, 0, ...c, ...c, ...corners[(i + 1) % 4]);
  });
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.Float32BufferAttribute(vertices, 3));
  const group = new THREE.Group();
  group.add(new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ color: COLORS.sensor })));
  group.add(new THREE.AxesHelper(0.03));
  group.visible = false;
  return group;
}

export class CellView {
  /** A view filling `container` (an element with a size); throws when WebGL is not available. */
  constructor(container) {
    this.container = container;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    const canvas = this.renderer.domElement;
    canvas.tabIndex = 0;
    canvas.setAttribute("aria-label", "3D view of the job; arrow keys pan, buttons zoom and reset");
    container.append(canvas);

    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(COLORS.background);
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.005, 50);
    this.camera.up.set(0, 0, 1);
    const grid = new THREE.GridHelper(1.2, 24, COLORS.grid, COLORS.grid);
    grid.rotation.x = Math.PI / 2; // the table plane z = 0
    this.scene.add(grid, new THREE.AxesHelper(0.1));

    this.cloud = new THREE.Points(new THREE.BufferGeometry(),
      new THREE.PointsMaterial({ size: 2.5, sizeAttenuation: false, vertexColors: true }));
    this.path = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: COLORS.path }));
    this.sensor = frustum();
    this.roi = boxEdges(COLORS.roi);
    this.packing = boxEdges(COLORS.packing);
    this.scene.add(this.cloud, this.path, this.sensor, this.roi, this.packing);

    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.listenToKeyEvents(canvas);
    this.controls.addEventListener("change", () => this.render());
    this.count = 0;
    this.fitted = false;
    this.resetView();
    this.resizer = new ResizeObserver(() => this.resize());
    this.resizer.observe(container);
    this.resize();
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.container;
    if (w === 0 || h === 0) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    if (this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = null;
      this.renderer.render(this.scene, this.camera);
    });
  }

  /** The cloud: `positions` x, y, z per point [m]; coloured from blue (low) to amber (high). The first
   *  cloud with points frames the view. */
  setCloud(positions) {
    const count = positions.length / 3;
    let lo = Infinity;
    let hi = -Infinity;
    for (let i = 2; i < positions.length; i += 3) {
      lo = Math.min(lo, positions[i]);
      hi = Math.max(hi, positions[i]);
    }
    const colors = new Float32Array(positions.length);
    const color = new THREE.Color();
    for (let i = 0; i < count; i += 1) {
      color.lerpColors(LOW, HIGH, hi > lo ? (positions[3 * i + 2] - lo) / (hi - lo) : 0.5);
      colors.set([color.r, color.g, color.b], 3 * i);
    }
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
    geometry.setAttribute("color", new THREE.BufferAttribute(colors, 3));
    this.cloud.geometry.dispose();
    this.cloud.geometry = geometry;
    this.count = count;
    if (!this.fitted && count > 0) this.resetView();
    this.render();
  }

  /** The sensor's path: [[x, y, z], ...] [m]. */
  setPath(points) {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.Float32BufferAttribute(points.flat(), 3));
    this.path.geometry.dispose();
    this.path.geometry = geometry;
    this.render();
  }

  /** The sensor's pose: origin `xyz` [m] and rotation `quatXyzw`, base frame. */
  setSensor(xyz, quatXyzw) {
    this.sensor.position.set(...xyz);
    this.sensor.quaternion.set(...quatXyzw);
    this.sensor.visible = true;
    this.render();
  }

  /** The ROI box: [[min x, y, z], [max x, y, z]] [m], or null to hide it. */
  setRoi(box) {
    this.roi.visible = Boolean(box);
    if (box) {
      const [lo, hi] = box;
      this.roi.position.set((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2);
      this.roi.scale.set(Math.max(hi[0] - lo[0], 1e-4), Math.max(hi[1] - lo[1], 1e-4), Math.max(hi[2] - lo[2], 1e-4));
      this.roi.rotation.set(0, 0, 0);
    }
    this.render();
  }

  /** The packing box of a packing job (result.json's packing: `dims_m` [l, w, h] and `box` {center_xy_m,
   *  yaw_rad, z_min_m}), or null to hide it. */
  setPackingBox(packing) {
    const shown = Boolean(packing && packing.dims_m && packing.box);
    this.packing.visible = shown;
    if (shown) {
      const [l, w, h] = packing.dims_m;
      const { center_xy_m: c, yaw_rad: yaw, z_min_m: z } = packing.box;
      this.packing.position.set(c[0], c[1], z + h / 2);
      this.packing.scale.set(l, w, h);
      this.packing.rotation.set(0, 0, yaw);
    }
    this.render();
  }

  /** Frame what is shown: the cloud, the boxes and the path, seen from the front left, above. */
  resetView() {
    const box = new THREE.Box3();
    for (const object of [this.cloud, this.roi, this.packing]) {
      if (object.visible) box.expandByObject(object);
    }
    if (box.isEmpty()) box.set(new THREE.Vector3(0.25, -0.2, 0), new THREE.Vector3(0.65, 0.2, 0.3));
    const center = box.getCenter(new THREE.Vector3());
    const size = Math.max(box.getSize(new THREE.Vector3()).length(), 0.15);
    const direction = new THREE.Vector3(-0.9, -1.1, 0.9).normalize();
    this.camera.position.copy(center).addScaledVector(direction, size * 1.15);
    this.controls.target.copy(center);
    this.controls.update();
    this.fitted = this.count > 0;
    this.render();
  }

  /** Move the camera towards the target (`factor` < 1) or away from it (> 1). */
  zoom(factor) {
    const offset = this.camera.position.clone().sub(this.controls.target).multiplyScalar(factor);
    this.camera.position.copy(this.controls.target).add(offset);
    this.controls.update();
    this.render();
  }

  dispose() {
    this.resizer.disconnect();
    this.controls.dispose();
    this.renderer.dispose();
    this.renderer.forceContextLoss();
  }
}
