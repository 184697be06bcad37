// The 3D view: the skin (translucent), the bone mesh inside it, joint centres (hover: the joint's OpenSim
// name and coordinates), a scan's points and per-vertex error colours. Renders on demand, not every frame.
import * as THREE from "three";
import { OrbitControls } from "./vendor/OrbitControls.js";

const SKIN = 0xe0b49a;
const BONE = 0xf2ecd9;
const JOINT = 0x2f6fde;

/** Diverging blue-to-red colour for t in [0, 1] (the legend's gradient). */
export function errorColour(t, out) {
  const stops = [[0.17, 0.48, 0.71], [0.67, 0.85, 0.91], [1.0, 1.0, 0.75], [0.99, 0.68, 0.38], [0.84, 0.1, 0.11]];
  const x = Math.min(Math.max(t, 0), 1) * (stops.length - 1);
  const i = Math.min(Math.floor(x), stops.length - 2);
  const f = x - i;
  for (let k = 0; k < 3; k++) out[k] = stops[i][k] * (1 - f) + stops[i + 1][k] * f;
  return out;
}

function meshOf(material) {
  const geometry = new THREE.BufferGeometry();
  const mesh = new THREE.Mesh(geometry, material);
  mesh.visible = false;
  return mesh;
}

/**
 * Whether WebGL runs on the CPU (SwiftShader, llvmpipe: a machine or browser without a GPU), where 4x
 * multisampling doubles a frame's time: the view leaves edges unsmoothed there. A probe context tells.
 */
function softwareWebGL() {
  const gl = document.createElement("canvas").getContext("webgl2");
  if (!gl) return true;
  const info = gl.getExtension("WEBGL_debug_renderer_info");
  const name = info ? String(gl.getParameter(info.UNMASKED_RENDERER_WEBGL)) : "";
  gl.getExtension("WEBGL_lose_context")?.loseContext();
  return /swiftshader|llvmpipe|software/i.test(name);
}

export class View {
  constructor(canvas, tooltip) {
    this.canvas = canvas;
    this.tooltip = tooltip;
    this.software = softwareWebGL();
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: !this.software, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
    this.renderer.setClearColor(0xf7f8fa);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(35, 1, 0.01, 100);
    // OpenSim's frame: x forward, y up, z to the right; the camera looks at the body's front-right
    this.camera.position.set(3.0, 0.4, 1.4);
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.target.set(0, 0, 0);
    this.controls.addEventListener("change", () => this.render());
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x8a8f99, 2.2));
    const sun = new THREE.DirectionalLight(0xffffff, 1.6);
    sun.position.set(2, 4, 3);
    this.scene.add(sun);
    this.skin = meshOf(new THREE.MeshLambertMaterial({
      color: SKIN, transparent: true, opacity: 0.45, depthWrite: false, side: THREE.DoubleSide,
    }));
    this.skin.renderOrder = 2;
    this.bones = meshOf(new THREE.MeshLambertMaterial({ color: BONE }));
    this.points = new THREE.Points(new THREE.BufferGeometry(),
      new THREE.PointsMaterial({ color: 0x56606e, size: 2, sizeAttenuation: false, transparent: true, opacity: 0.7 }));
    this.points.visible = false;
    this.joints = new THREE.Group();
    this.jointMaterial = new THREE.MeshBasicMaterial({ color: JOINT, depthTest: false, transparent: true });
    this.jointInfo = [];
    this.scene.add(this.bones, this.skin, this.points, this.joints);
    this.layers = { skin: true, bones: true, joints: true, scan: true };
    this.raycaster = new THREE.Raycaster();
    canvas.addEventListener("pointermove", (e) => this.hover(e));
    canvas.addEventListener("pointerleave", () => { this.tooltip.hidden = true; });
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
    this.warm();
  }

  /**
   * Compile the skin's and bones' shaders now: the GPU process compiles them while the page waits for
   * its first body, instead of after it (a software WebGL takes hundreds of milliseconds for it).
   */
  warm() {
    const triangle = new THREE.BufferGeometry();
    triangle.setAttribute("position", new THREE.BufferAttribute(new Float32Array(9), 3));
    triangle.setAttribute("normal", new THREE.BufferAttribute(new Float32Array(9), 3));
    const scene = new THREE.Scene();
    scene.add(...this.scene.children.filter((o) => o.isLight).map((light) => light.clone()));
    scene.add(new THREE.Mesh(triangle, this.skin.material), new THREE.Mesh(triangle, this.bones.material));
    scene.add(new THREE.Mesh(triangle, this.jointMaterial));
    this.renderer.compile(scene, this.camera);
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.canvas;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    this.skin.visible = this.layers.skin && this.skin.geometry.hasAttribute("position");
    this.bones.visible = this.layers.bones && this.bones.geometry.hasAttribute("position");
    this.joints.visible = this.layers.joints;
    this.points.visible = this.layers.scan && this.points.geometry.hasAttribute("position");
    this.renderer.render(this.scene, this.camera);
    this.frames = (this.frames || 0) + 1;
  }

  /** Wait until the frame is on the canvas: the draw calls run after render() returns (in the GPU
   * process); reading one pixel waits for them. */
  finish() {
    const gl = this.renderer.getContext();
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
  }

  static setMesh(mesh, vertices, faces) {
    const geometry = mesh.geometry;
    const position = geometry.getAttribute("position");
    if (position && position.array.length === vertices.length && !faces) {
      position.array.set(vertices);
      position.needsUpdate = true;
    } else {
      geometry.setAttribute("position", new THREE.BufferAttribute(Float32Array.from(vertices), 3));
    }
    if (faces) geometry.setIndex(new THREE.BufferAttribute(Uint32Array.from(faces), 1));
    geometry.computeVertexNormals();
    geometry.computeBoundingSphere();
  }

  /** The skin: vertices (V*3) metres, faces (F*3) given once (kept until new ones come). */
  setSkin(vertices, faces = null, colours = null) {
    View.setMesh(this.skin, vertices, faces);
    const material = this.skin.material;
    if (colours) {
      this.skin.geometry.setAttribute("color", new THREE.BufferAttribute(colours, 3));
      material.vertexColors = true;
      material.color.set(0xffffff);
    } else if (material.vertexColors) {
      this.skin.geometry.deleteAttribute("color");
      material.vertexColors = false;
      material.color.set(SKIN);
    }
    material.needsUpdate = true;
  }

  setBones(vertices, faces = null) {
    if (!vertices) {
      this.bones.geometry.deleteAttribute("position");
      return;
    }
    View.setMesh(this.bones, vertices, faces);
  }

  setOpacity(opacity) {
    const m = this.skin.material;
    m.opacity = opacity;
    m.transparent = opacity < 1;
    m.depthWrite = opacity >= 1;
    m.needsUpdate = true;
    this.render();
  }

  /** Joint centres: positions (J*3) and, per joint, {name, coordinates: [OpenSim coordinate names]}. */
  setJoints(positions, info) {
    if (this.joints.children.length !== info.length) {
      this.joints.clear();
      const geometry = new THREE.SphereGeometry(0.014, 12, 8);
      const material = this.jointMaterial;
      info.forEach((_, i) => {
        const s = new THREE.Mesh(geometry, material);
        s.renderOrder = 3;
        s.userData.index = i;
        this.joints.add(s);
      });
    }
    this.jointInfo = info;
    this.tooltip.hidden = true; // it named a joint of the body drawn before
    this.joints.children.forEach((s, i) => s.position.fromArray(positions, 3 * i));
  }

  /** Scan points (N*3) or null. */
  setPoints(points) {
    const geometry = new THREE.BufferGeometry();
    if (points) {
      geometry.setAttribute("position", new THREE.BufferAttribute(points, 3));
      geometry.computeBoundingSphere();
    }
    this.points.geometry.dispose();
    this.points.geometry = geometry;
  }

  /** Point the camera at what is shown (a scan may come in any frame and unit). */
  frame() {
    const box = new THREE.Box3();
    for (const o of [this.skin, this.points]) {
      if (o.geometry.hasAttribute("position")) box.expandByObject(o);
    }
    if (box.isEmpty()) return;
    const centre = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3()).length();
    const dir = this.camera.position.clone().sub(this.controls.target).normalize();
    this.controls.target.copy(centre);
    this.camera.position.copy(centre).addScaledVector(dir, size * 1.9);
    this.camera.near = size / 100;
    this.camera.far = size * 20;
    this.camera.updateProjectionMatrix();
    this.controls.update();
    this.render();
  }

  hover(event) {
    if (!this.layers.joints || !this.jointInfo.length) return;
    const r = this.canvas.getBoundingClientRect();
    const x = ((event.clientX - r.left) / r.width) * 2 - 1;
    const y = -((event.clientY - r.top) / r.height) * 2 + 1;
    this.raycaster.setFromCamera({ x, y }, this.camera);
    const hit = this.raycaster.intersectObjects(this.joints.children, false)[0];
    if (!hit) {
      this.tooltip.hidden = true;
      return;
    }
    const info = this.jointInfo[hit.object.userData.index];
    this.tooltip.textContent = [info.name, ...info.coordinates].join("\n");
    this.tooltip.style.left = `${event.clientX - r.left + 14}px`;
    this.tooltip.style.top = `${event.clientY - r.top + 8}px`;
    this.tooltip.hidden = false;
  }
}

/**
 * Per-vertex distance (metres) from each of `vertices` (V*3) to the nearest of `points` (N*3): a uniform
 * grid over the points, searched ring by ring around each vertex until the ring is farther than the best.
 */
export function nearestDistances(vertices, points) {
  const n = points.length / 3;
  const lo = [Infinity, Infinity, Infinity];
  const hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < n; i++) {
    for (let k = 0; k < 3; k++) {
      lo[k] = Math.min(lo[k], points[3 * i + k]);
      hi[k] = Math.max(hi[k], points[3 * i + k]);
    }
  }
  const extent = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 1e-6);
  const cell = Math.max(extent / Math.cbrt(n / 2), 1e-4);
  const dims = [0, 1, 2].map((k) => Math.max(1, Math.ceil((hi[k] - lo[k]) / cell) + 1));
  const key = (a, b, c) => (a * dims[1] + b) * dims[2] + c;
  const grid = new Map();
  for (let i = 0; i < n; i++) {
    const c = [0, 1, 2].map((k) => Math.floor((points[3 * i + k] - lo[k]) / cell));
    const id = key(c[0], c[1], c[2]);
    if (!grid.has(id)) grid.set(id, []);
    grid.get(id).push(i);
  }
  const out = new Float32Array(vertices.length / 3);
  for (let v = 0; v < out.length; v++) {
    const p = [vertices[3 * v], vertices[3 * v + 1], vertices[3 * v + 2]];
    const c = p.map((x, k) => Math.min(Math.max(Math.floor((x - lo[k]) / cell), 0), dims[k] - 1));
    let best = Infinity;
    for (let ring = 0; ring < Math.max(...dims); ring++) {
      // the cells of this ring's shell that lie inside the grid
      for (let a = Math.max(c[0] - ring, 0); a <= Math.min(c[0] + ring, dims[0] - 1); a++) {
        for (let b = Math.max(c[1] - ring, 0); b <= Math.min(c[1] + ring, dims[1] - 1); b++) {
          for (let d = Math.max(c[2] - ring, 0); d <= Math.min(c[2] + ring, dims[2] - 1); d++) {
            const onShell = Math.max(Math.abs(a - c[0]), Math.abs(b - c[1]), Math.abs(d - c[2])) === ring;
            const bucket = onShell && grid.get(key(a, b, d));
            if (!bucket) continue;
            for (const i of bucket) {
              const dx = points[3 * i] - p[0];
              const dy = points[3 * i + 1] - p[1];
              const dz = points[3 * i + 2] - p[2];
              best = Math.min(best, dx * dx + dy * dy + dz * dz);
            }
          }
        }
      }
      // every point in a farther ring is at least ring * cell away (minus the vertex's offset in its cell)
      if (best < Infinity && Math.sqrt(best) <= ring * cell) break;
    }
    out[v] = Math.sqrt(best);
  }
  return out;
}
