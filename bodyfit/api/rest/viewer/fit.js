// Fit: a dropped scan goes to POST /v1/fit/scan (NDJSON progress); the scan's points, the fitted body
// coloured by its distance to the scan, the bones inside it, and the fit's report are shown.
import { BufferAttribute, BufferGeometry, Matrix4 } from "three";
import { OBJLoader } from "./vendor/OBJLoader.js";
import { PCDLoader } from "./vendor/PCDLoader.js";
import { PLYLoader } from "./vendor/PLYLoader.js";
import { STLLoader } from "./vendor/STLLoader.js";
import { parseNpz, postJSON, stream, wireArray } from "./api.js";
import { hideError, showError } from "./app.js";
import { errorColour, nearestDistances } from "./view.js";

const $ = (id) => document.getElementById(id);
const MAX_POINTS = 60000;
const COLOUR_MAX_MM = 20;

function positionsOf(object) {
  const out = [];
  object.traverse((o) => {
    const p = o.geometry && o.geometry.getAttribute("position");
    if (p) out.push(p.array);
  });
  const all = new Float32Array(out.reduce((n, a) => n + a.length, 0));
  let at = 0;
  for (const a of out) { all.set(a, at); at += a.length; }
  return all;
}

/**
 * parse() of a three.js loader without its bounding sphere: the viewer keeps the finite points and frames
 * them itself, and a scan's "no return" NaN points (organised Kinect clouds) would make three log an error.
 */
function parsed(parse) {
  const original = BufferGeometry.prototype.computeBoundingSphere;
  BufferGeometry.prototype.computeBoundingSphere = function unused() {};
  try {
    return parse();
  } finally {
    BufferGeometry.prototype.computeBoundingSphere = original;
  }
}

/** The scan's points (N*3, finite, at most MAX_POINTS by an even stride) from the file's bytes. */
export function scanPoints(name, buffer) {
  const ext = name.split(".").pop().toLowerCase();
  let raw;
  if (ext === "ply") raw = parsed(() => new PLYLoader().parse(buffer)).getAttribute("position").array;
  else if (ext === "stl") raw = parsed(() => new STLLoader().parse(buffer)).getAttribute("position").array;
  else if (ext === "pcd") raw = parsed(() => new PCDLoader().parse(buffer)).geometry.getAttribute("position").array;
  else if (ext === "obj") raw = positionsOf(parsed(() => new OBJLoader().parse(new TextDecoder().decode(buffer))));
  else if (ext === "npz") {
    const arrays = parseNpz(buffer);
    raw = Float32Array.from((arrays.points || arrays.vertices).data);
  } else return null;
  const n = raw.length / 3;
  const stride = Math.max(1, Math.ceil(n / MAX_POINTS));
  const out = [];
  for (let i = 0; i < n; i += stride) {
    const x = raw[3 * i], y = raw[3 * i + 1], z = raw[3 * i + 2];
    if (Number.isFinite(x) && Number.isFinite(y) && Number.isFinite(z)) out.push(x, y, z);
  }
  return new Float32Array(out);
}

function mm(value) {
  return value === null || value === undefined ? "–" : `${value.toFixed(2)} mm`;
}

function statsRow(label, stats) {
  if (!stats) return "";
  return `<tr><td>${label}</td><td>mean <b data-key="${label}-mean">${mm(stats.mean)}</b>, median ${mm(stats.median)},
    p95 ${mm(stats.p95)}, max ${mm(stats.max)}</td></tr>`;
}

export class FitMode {
  constructor(view, model, synth) {
    this.view = view;
    this.model = model;
    this.synth = synth;
    this.result = null;
    this.scan = null;
    this.errors = null;
    bindDrop($("fit-drop"), $("fit-file"), (file) => this.fit(file));
  }

  enter() {
    this.view.setBones(null);
    if (this.result) this.show();
    else {
      this.view.setPoints(this.scan);
      this.view.render();
    }
  }

  leave() {
    this.view.setPoints(null);
    $("legend").hidden = true;
  }

  /** The scan's points in the view while it is fitted (a file the browser cannot read: none). */
  async draw(file) {
    try {
      this.scan = scanPoints(file.name, await file.arrayBuffer());
    } catch (_) {
      this.scan = null; // the fit goes on: the service reads more variants than three.js's loaders
    }
    if (this.scan && !this.scan.length) this.scan = null;
    this.view.setPoints(this.scan);
    this.view.frame();
  }

  form(file) {
    const form = new FormData();
    form.append("file", file, file.name);
    form.append("units", $("fit-units").value);
    for (const hint of ["up", "facing", "pose", "sex"]) {
      const value = $(`fit-${hint}`).value;
      if (value) form.append(hint, value);
    }
    if ($("fit-height").value) form.append("height_m", $("fit-height").value);
    return form;
  }

  async fit(file) {
    const bar = $("fit-progress");
    const message = $("fit-message");
    this.result = null;
    window.bodyfitViewer.fit = null;
    $("fit-report").innerHTML = `<tr><td>fitting ${file.name.replace(/</g, "&lt;")}…</td></tr>`;
    $("fit-reasons").innerHTML = "";
    try {
      this.scan = null;
      this.view.setPoints(null);
      message.textContent = `uploading ${(file.size / 1e6).toFixed(1)} MB…`;
      let drawn = false;
      const onEvent = (event) => {
        if (event.event !== "progress") return;
        // the service checks a scan before it streams: the first event says the file is one
        if (!drawn) drawn = this.draw(file);
        bar.max = Math.max(event.total, 1);
        bar.value = event.done;
        message.textContent = `${event.stage} ${event.done}/${event.total}: ${event.message}`;
      };
      this.result = await stream("/v1/fit/scan", this.form(file), onEvent);
      hideError();
      await (drawn || this.draw(file));
      await this.bones();
      this.show();
      message.textContent = `fitted as ${this.result.fitted_as} in ${this.result.report.seconds.toFixed(1)} s`;
      window.bodyfitViewer.fit = { result: this.result, meanErrorMm: this.meanErrorMm };
    } catch (error) {
      message.textContent = "the fit failed (see the message above)";
      showError(error);
    }
  }

  /** The bone mesh of the fitted parameters, moved from the model's frame into the scan's. */
  async bones() {
    const a = this.result.arrays;
    const body = {
      shape: [Array.from(wireArray(a.shape).data)],
      coordinates: [Array.from(wireArray(a.coordinates).data)],
      root: [Array.from(wireArray(a.root).data)],
      skeleton: true,
      faces: true,
    };
    const arrays = parseNpz(await postJSON("/v1/synthesize", body));
    const bones = arrays.bones.data;
    if (a.to_model) {
      // x_model = M [x_input, 1]: the bones (model frame) go to the scan's frame through M's inverse
      const toInput = new Matrix4().set(...wireArray(a.to_model).data).invert();
      new BufferAttribute(bones, 3).applyMatrix4(toInput);
    }
    this.boneArrays = { bones, faces: arrays.bone_faces.data };
  }

  show() {
    const a = this.result.arrays;
    const vertices = wireArray(a.vertices).data;
    let colours = null;
    if (this.scan && this.scan.length) {
      this.errors = nearestDistances(vertices, this.scan);
      colours = new Float32Array(vertices.length);
      const rgb = [0, 0, 0];
      let sum = 0;
      this.errors.forEach((d, i) => {
        sum += d;
        colours.set(errorColour((d * 1000) / COLOUR_MAX_MM, rgb), 3 * i);
      });
      this.meanErrorMm = (sum / this.errors.length) * 1000;
      $("legend-max").textContent = `${COLOUR_MAX_MM} mm`;
      $("legend").hidden = false;
    }
    this.view.setSkin(vertices, this.synth.faces, colours);
    if (this.boneArrays) this.view.setBones(this.boneArrays.bones, this.boneArrays.faces);
    this.view.setJoints(wireArray(a.joints).data, this.model.jointInfo);
    this.view.setPoints(this.scan);
    this.view.frame();
    this.report();
  }

  report() {
    const r = this.result.report;
    const rows = [
      `<tr><td>fitted as</td><td id="fit-fitted-as">${this.result.fitted_as}</td></tr>`,
      `<tr><td>confident</td><td id="fit-confident" class="${r.confident ? "yes" : "no"}">${r.confident ? "yes" : "no"}</td></tr>`,
      statsRow("distances", r.distances),
      statsRow("scan to model", r.scan_to_model),
      statsRow("model to scan", r.model_to_scan),
      r.predicted_error_mm === null || r.predicted_error_mm === undefined ? "" :
        `<tr><td>predicted error</td><td>${mm(r.predicted_error_mm)}${r.predicted_error_interval_mm ?
          ` (${r.predicted_error_interval_mm.map((x) => x.toFixed(1)).join("–")} mm)` : ""}</td></tr>`,
      this.meanErrorMm === undefined ? "" :
        `<tr><td>colours</td><td>body to nearest scan point, mean ${mm(this.meanErrorMm)}</td></tr>`,
      `<tr><td>limit violations</td><td>${r.limit_violations}</td></tr>`,
      `<tr><td>iterations</td><td>${r.iterations}</td></tr>`,
      `<tr><td>seconds</td><td>${r.seconds.toFixed(2)}</td></tr>`,
    ];
    $("fit-report").innerHTML = rows.join("");
    const notes = [...r.reasons.map((x) => `reason: ${x}`), ...((r.extra && r.extra.observations) || [])];
    $("fit-reasons").innerHTML = notes.map((x) => `<li>${x.replace(/</g, "&lt;")}</li>`).join("");
  }
}

/** A drop zone with its file input: a file dropped or chosen calls onFile(file). */
export function bindDrop(zone, input, onFile) {
  zone.addEventListener("dragover", (e) => { e.preventDefault(); zone.classList.add("over"); });
  zone.addEventListener("dragleave", () => zone.classList.remove("over"));
  zone.addEventListener("drop", (e) => {
    e.preventDefault();
    zone.classList.remove("over");
    if (e.dataTransfer.files.length) onFile(e.dataTransfer.files[0]);
  });
  input.addEventListener("change", () => {
    if (input.files.length) onFile(input.files[0]);
    input.value = "";
  });
}
