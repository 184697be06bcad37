// Synthesize: sliders for the shape coefficients and every coordinate (grouped by joint, limits shown); the
// body follows live through POST /v1/synthesize (npz, the service's fastest format).
import { answered, parseNpz, postJSON } from "./api.js";
import { hideError, jointOf, showError } from "./app.js";

const $ = (id) => document.getElementById(id);
const DEG = 180 / Math.PI;
const SHAPE_RANGE = 3;

/** A coordinate's value as shown: degrees for angles, metres for translations, plain for coefficients. */
export function formatValue(value, unit) {
  if (unit === "rad") return `${(value * DEG).toFixed(1)}°`;
  return unit === "m" ? `${value.toFixed(3)} m` : value.toFixed(2);
}

// step "any": a stepped range counts its steps from min, so a limit such as -1.5708 would move the neutral
// pose's 0 to the nearest step (-0.0008); "any" keeps 0 (and every limit) exact
function slider(parent, { id, label, min, max, value, unit }, onInput, onChange) {
  const row = document.createElement("div");
  row.className = "slider";
  row.innerHTML = `<label for="${id}" title="${label}">${label}</label>
    <input type="range" id="${id}" min="${min}" max="${max}" step="any" value="${value}">
    <output></output>
    <div class="limits"><span>${formatValue(min, unit)}</span><span>${formatValue(max, unit)}</span></div>`;
  const input = row.querySelector("input");
  const output = row.querySelector("output");
  const show = () => { output.textContent = formatValue(Number(input.value), unit); };
  show();
  input.addEventListener("input", () => { show(); onInput(); });
  input.addEventListener("change", onChange);
  parent.append(row);
  return input;
}

export class SynthMode {
  constructor(view, model) {
    this.view = view;
    this.model = model;
    this.faces = null;
    this.boneFaces = null;
    this.inFlight = false;
    this.pending = null;
    this.timings = [];
    this.last = null;
    this.buildSliders();
    $("synth-reset").addEventListener("click", () => this.reset());
  }

  buildSliders() {
    const { info } = this.model;
    const shapeBox = $("shape-sliders");
    this.shapeInputs = [];
    for (let i = 0; i < info.shape.n_shape; i++) {
      const bone = i < info.shape.n_bone;
      const label = bone ? `bone ${i + 1}` : `identity ${i - info.shape.n_bone + 1}`;
      this.shapeInputs.push(slider(shapeBox, {
        id: `shape-${i}`, label, min: -SHAPE_RANGE, max: SHAPE_RANGE, value: 0, unit: "",
      }, () => this.request(false), () => this.request(true)));
    }
    const groups = new Map();
    for (const [index, dof] of info.dofs.entries()) {
      const joint = jointOf(dof.name, info.joint_names);
      if (!groups.has(joint)) groups.set(joint, []);
      groups.get(joint).push({ ...dof, index });
    }
    this.dofInputs = [];
    const box = $("dof-sliders");
    for (const [joint, dofs] of groups) {
      const details = document.createElement("details");
      details.open = ["hip_r", "knee_r", "ankle_r"].includes(joint);
      details.innerHTML = `<summary>${joint} <small>(${dofs.length})</small></summary>`;
      box.append(details);
      for (const dof of dofs) {
        const value = Math.min(Math.max(0, dof.min), dof.max);
        const input = slider(details, {
          id: `dof-${dof.name}`, label: dof.name, min: dof.min, max: dof.max, value, unit: dof.unit,
        }, () => this.request(false), () => this.request(true));
        this.dofInputs[dof.index] = input; // the request's order: the model's, not the groups'
      }
    }
  }

  params() {
    return {
      shape: [this.shapeInputs.map((s) => Number(s.value))],
      coordinates: [this.dofInputs.map((s) => Number(s.value))],
    };
  }

  /**
   * The first body: the skin alone (drawn sooner), then the bones when shown. `first`: the page's early
   * request for the mean body in the neutral pose (a fetch promise), used where the sliders start there.
   */
  async start(first) {
    const neutral = this.model.dofs.every((d) => d.min <= 0 && d.max >= 0);
    if (first && neutral) {
      const began = performance.now();
      this.last = parseNpz(await (await answered(first)).arrayBuffer());
      this.timings.push({ ms: performance.now() - began, bones: false });
      window.bodyfitViewer.marks.body = performance.now();
      this.show(this.last, false); // drawn once, by frame() below
    } else {
      await this.request(false);
    }
    this.view.frame();
    this.view.finish();
    window.bodyfitViewer.marks.drawn = performance.now();
    if (this.view.layers.bones) this.request(true);
  }

  enter() {
    if (this.last && !this.last.bones) this.view.setBones(null); // not the bones of another mode's body
    if (this.last) this.show(this.last, false);
    this.view.setPoints(null);
    this.view.frame();
  }

  leave() {}

  reset() {
    this.shapeInputs.forEach((s) => { s.value = 0; s.dispatchEvent(new Event("input")); });
    this.dofInputs.forEach((s, i) => {
      const d = this.model.dofs[i];
      s.value = Math.min(Math.max(0, d.min), d.max);
      s.dispatchEvent(new Event("input"));
    });
    this.request(true);
  }

  /**
   * Ask for the body at the sliders' values. While dragging (full = false) only the skin, the fastest
   * answer; on release the bone mesh too. One request at a time: values that change meanwhile are sent
   * once it answers, so the body follows the slider without a queue of stale requests.
   */
  async request(full) {
    const withBones = full && this.view.layers.bones;
    if (this.inFlight) {
      this.pending = this.pending === true || withBones;
      return;
    }
    this.inFlight = true;
    try {
      const body = { ...this.params(), format: "npz", skeleton: withBones, faces: !this.faces || (withBones && !this.boneFaces) };
      const began = performance.now();
      const arrays = parseNpz(await postJSON("/v1/synthesize", body));
      const ms = performance.now() - began;
      this.timings.push({ ms, bones: withBones });
      $("synth-ms").textContent = ms.toFixed(0);
      this.last = arrays;
      if (window.bodyfitViewer.tab === "synth") this.show(arrays);
      hideError();
    } catch (error) {
      showError(error);
    } finally {
      this.inFlight = false;
    }
    if (this.pending !== null) {
      const again = this.pending;
      this.pending = null;
      await this.request(again);
    }
  }

  /** Draw a synthesize answer (npz arrays of one body); `draw` false: leave the render to the caller. */
  show(arrays, draw = true) {
    if (arrays.faces) this.faces = arrays.faces.data;
    if (arrays.bone_faces) this.boneFaces = arrays.bone_faces.data;
    const vertices = arrays.vertices.data;
    const fresh = arrays.faces ? this.faces : null;
    this.view.setSkin(vertices, fresh || (this.view.skin.geometry.index ? null : this.faces));
    if (arrays.bones) this.view.setBones(arrays.bones.data, arrays.bone_faces ? this.boneFaces : null);
    this.view.setJoints(arrays.joints.data, this.model.jointInfo);
    if (draw) this.view.render();
    let lo = Infinity;
    let hi = -Infinity;
    for (let i = 1; i < vertices.length; i += 3) {
      lo = Math.min(lo, vertices[i]);
      hi = Math.max(hi, vertices[i]);
    }
    $("synth-stature").textContent = ((hi - lo) * 1000).toFixed(1);
    const rows = this.model.joints.map((name, j) => {
      const p = Array.from(arrays.joints.data.slice(3 * j, 3 * j + 3), (x) => x.toFixed(3)).join(", ");
      return `<tr><td>${name}</td><td>${p}</td></tr>`;
    });
    $("synth-joints").innerHTML = rows.join("");
  }
}
