// The viewer's entry: model info, tabs, layers, the error banner, and the three modes (synthesize, fit,
// upgrade). `window.bodyfitViewer` exposes the state the end-to-end test and the benchmark read.
import { ApiError, answered, getJSON } from "./api.js";
import { FitMode } from "./fit.js";
import { SynthMode } from "./synth.js";
import { UpgradeMode } from "./upgrade.js";
import { View } from "./view.js";

const $ = (id) => document.getElementById(id);

/** The joint that each OpenSim coordinate turns (the model's joint names; side from the suffix). Every
 * pattern matches the whole name, which the replacement then turns into the joint's. */
const JOINT_OF = [
  [/^pelvis_\w+$/, "pelvis"],
  [/^lumbar_\w+$/, "lumbosacral"],
  [/^thorax_\w+$/, "thoracolumbar"],
  [/^neck_\w+$/, "cervicothoracic"],
  [/^hip_\w+_([rl])$/, "hip_$1"],
  [/^knee_\w+_([rl])$/, "knee_$1"],
  [/^(?:ankle|subtalar)_\w+_([rl])$/, "ankle_$1"],
  [/^mtp_\w+_([rl])$/, "mtp_$1"],
  [/^(?:scapula|arm)_\w+_([rl])$/, "shoulder_$1"],
  [/^(?:elbow|pro_sup)\w*_([rl])$/, "elbow_$1"],
  [/^wrist_\w+_([rl])$/, "wrist_$1"],
];

export function jointOf(dof, joints) {
  for (const [pattern, joint] of JOINT_OF) {
    if (pattern.test(dof)) {
      const name = dof.replace(pattern, joint);
      if (joints.includes(name)) return name;
    }
  }
  return "other";
}

/** Shows an error: an API problem as its title, detail and field; anything else as its message. */
export function showError(error) {
  const problem = error instanceof ApiError ? error.problem : null;
  $("error-title").textContent = problem ? `${problem.title || "Error"} (${problem.status})` : "Error";
  $("error-detail").textContent = problem ? problem.detail : String(error.message || error);
  $("error-field").textContent = problem && problem.field ? `field: ${problem.field}` : "";
  $("error").hidden = false;
  window.bodyfitViewer.errors.push(problem || { detail: String(error.message || error) });
}

export function hideError() {
  $("error").hidden = true;
}

export function setStatus(text) {
  $("status").textContent = text;
}

function bindLayers(view) {
  for (const layer of ["skin", "bones", "joints", "scan"]) {
    $(`show-${layer}`).addEventListener("change", (e) => {
      view.layers[layer] = e.target.checked;
      view.render();
      const { modes, tab } = window.bodyfitViewer;
      if (layer === "bones" && e.target.checked && tab === "synth") modes.synth.request(true); // fetch them
    });
  }
  $("skin-opacity").addEventListener("input", (e) => view.setOpacity(Number(e.target.value)));
}

function bindTabs(modes) {
  const buttons = document.querySelectorAll("#tabs button");
  buttons.forEach((button) => button.addEventListener("click", () => {
    buttons.forEach((b) => b.classList.toggle("active", b === button));
    document.querySelectorAll("[data-panel]").forEach((p) => { p.hidden = p.dataset.panel !== button.dataset.tab; });
    Object.entries(modes).forEach(([name, mode]) => (name === button.dataset.tab ? mode.enter() : mode.leave()));
    window.bodyfitViewer.tab = button.dataset.tab;
  }));
}

async function main() {
  window.bodyfitViewer = { ready: false, errors: [], tab: "synth", marks: {} };
  window.addEventListener("unhandledrejection", (e) => showError(e.reason));
  $("error-close").addEventListener("click", hideError);
  const marks = { scripts: performance.now() }; // ms from the navigation's start: where a load's time goes
  window.bodyfitViewer.marks = marks;
  const view = new View($("view"), $("tooltip"));
  marks.webgl = performance.now();
  bindLayers(view);
  const first = window.bodyfitFirst || {};
  let info;
  for (;;) {
    try {
      info = await (first.model ? answered(first.model).then((r) => r.json()) : getJSON("/v1/model"));
      break;
    } catch (error) {
      // 503 while the model loads (GET /readyz says when): wait and ask again, showing why
      if (!(error instanceof ApiError) || error.problem.status !== 503) throw error;
      setStatus(error.problem.detail);
      first.model = first.body = null;
      await new Promise((r) => setTimeout(r, 1000));
    }
  }
  const model = {
    info,
    dofs: info.dofs,
    joints: info.joint_names,
    jointInfo: info.joint_names.map((name) => ({
      name,
      coordinates: info.dofs.filter((d) => jointOf(d.name, info.joint_names) === name).map((d) => d.name),
    })),
  };
  marks.model = performance.now();
  const synth = new SynthMode(view, model);
  marks.sliders = performance.now();
  const modes = { synth, fit: new FitMode(view, model, synth), upgrade: new UpgradeMode(view, model, synth) };
  Object.assign(window.bodyfitViewer, { view, model, modes });
  bindTabs(modes);
  await synth.start(first.body);
  setStatus(`model ${info.version}: ${info.dofs.length} coordinates, ${info.shape.n_shape} shape coefficients`);
  window.bodyfitViewer.ready = true;
  window.bodyfitViewer.readyMs = performance.now();
}

main().catch(showError);
