// Upgrade: a dropped AMASS-style npz goes to POST /v1/upgrade (NDJSON: progress, chunks of coordinates,
// then the summary and files); the result plays with a timeline (skin and skeleton posed by
// /v1/synthesize in batches), with plots of chosen coordinates and download links.
import { base64Blob, parseNpz, postJSON, stream, wireArray } from "./api.js";
import { hideError, showError } from "./app.js";
import { bindDrop } from "./fit.js";
import { formatValue } from "./synth.js";

const $ = (id) => document.getElementById(id);
const BATCH = 30;
const DEG = 180 / Math.PI;
const PLOTTED = ["hip_flexion_r", "hip_flexion_l", "knee_angle_r", "knee_angle_l", "ankle_angle_r", "ankle_angle_l"];
const COLOURS = ["#2f6fde", "#8fb3f0", "#d64545", "#f0a0a0", "#1b7f3b", "#8fd0a4", "#8a4fd6", "#c9a227"];
const MEDIA = { npz: "application/x-npz", json: "application/json", osim: "application/xml", mot: "text/plain" };

export class UpgradeMode {
  constructor(view, model, synth) {
    this.view = view;
    this.model = model;
    this.synth = synth;
    this.clear();
    bindDrop($("up-drop"), $("up-file"), (file) => this.upgrade(file));
    $("up-play").addEventListener("click", () => (this.playing ? this.pause() : this.play()));
    $("up-frame").addEventListener("input", (e) => { this.pause(); this.seek(Number(e.target.value)); });
    const select = $("up-coords");
    select.innerHTML = model.dofs.map((d) => `<option ${PLOTTED.includes(d.name) ? "selected" : ""}>${d.name}</option>`).join("");
    select.addEventListener("change", () => { this.plot(); this.values(); });
  }

  clear() {
    this.frames = 0;
    this.coordinates = [];
    this.root = [];
    this.joints = [];
    this.errorMm = [];
    this.bodies = new Map();
    this.loading = new Map();
    this.current = 0;
    this.playing = false;
    this.result = null;
  }

  enter() {
    $("timeline").hidden = !this.result;
    this.view.setPoints(null);
    if (this.result) this.seek(this.current).then(() => this.view.frame());
  }

  leave() {
    this.pause();
    $("timeline").hidden = true;
  }

  form(file) {
    const form = new FormData();
    form.append("file", file, file.name);
    if ($("up-sex").value) form.append("sex", $("up-sex").value);
    if ($("up-height").value) form.append("height_m", $("up-height").value);
    if ($("up-mass").value) form.append("mass_kg", $("up-mass").value);
    return form;
  }

  onEvent(event) {
    if (event.event === "progress") {
      $("up-progress").max = Math.max(event.total, 1);
      $("up-progress").value = event.done;
      $("up-message").textContent = `${event.stage} ${event.done}/${event.total}: ${event.message}`;
    } else if (event.event === "chunk") {
      const c = wireArray(event.arrays.coordinates);
      const r = wireArray(event.arrays.root);
      const j = wireArray(event.arrays.joints);
      const e = wireArray(event.arrays.error_mm);
      const n = this.model.dofs.length;
      const nj = this.model.joints.length;
      for (let f = 0; f < event.stop - event.start; f++) {
        this.coordinates.push(Array.from(c.data.subarray(f * n, (f + 1) * n)));
        this.root.push(Array.from(r.data.subarray(3 * f, 3 * f + 3)));
        this.joints.push(j.data.slice(f * nj * 3, (f + 1) * nj * 3));
        this.errorMm.push(e.data[f]);
      }
    }
  }

  async upgrade(file) {
    this.pause();
    this.clear();
    window.bodyfitViewer.upgrade = null;
    $("up-files").innerHTML = "";
    try {
      this.result = await stream("/v1/upgrade", this.form(file), (e) => this.onEvent(e));
      hideError();
      this.frames = this.coordinates.length;
      this.shape = Array.from(wireArray(this.result.arrays.shape).data);
      this.rate = this.result.summary.frame_rate || 30;
      this.links(file.name.replace(/\.npz$/i, ""));
      this.summary();
      $("up-frame").max = this.frames - 1;
      $("timeline").hidden = false;
      this.plot();
      await this.seek(0);
      this.view.frame();
      $("up-message").textContent = `${this.frames} frames at ${this.rate.toFixed(0)} Hz`;
      window.bodyfitViewer.upgrade = { frames: this.frames, summary: this.result.summary };
    } catch (error) {
      $("up-message").textContent = "the upgrade failed (see the message above)";
      showError(error);
    }
  }

  links(stem) {
    const box = $("up-files");
    for (const [kind, data] of Object.entries(this.result.files)) {
      const a = document.createElement("a");
      a.href = URL.createObjectURL(base64Blob(data, MEDIA[kind]));
      a.download = `${stem}.${kind}`;
      a.textContent = `${stem}.${kind}`;
      box.append(a);
    }
  }

  summary() {
    const s = this.result.summary;
    // error_mm is NaN where no reference exists (path b: no SMPL model to compare with)
    const known = this.errorMm.filter(Number.isFinite);
    const mean = known.length ? `${(known.reduce((a, b) => a + b, 0) / known.length).toFixed(2)} mm` : "–";
    const rows = [
      ["frames", `<span id="up-frames">${s.frames}</span> at ${s.frame_rate.toFixed(1)} Hz`],
      ["path", s.path],
      ["bad frames", s.bad_frames.length],
      ["mean error", mean],
      ["limit violations", s.limit_violations],
      ["largest frame jump", s.max_frame_jump_deg === null ? "–" : `${s.max_frame_jump_deg.toFixed(1)}°`],
      ["speed", `${s.fps.toFixed(1)} frames/s`],
    ];
    $("up-summary").innerHTML = rows.map(([k, v]) => `<tr><td>${k}</td><td>${v}</td></tr>`).join("");
    $("up-notes").innerHTML = s.notes.map((x) => `<li>${x.replace(/</g, "&lt;")}</li>`).join("");
  }

  /** Pose the batch of frames holding `frame` (skin, and bones when shown) through /v1/synthesize. */
  load(frame) {
    const batch = Math.floor(frame / BATCH);
    if (this.loading.has(batch)) return this.loading.get(batch);
    const start = batch * BATCH;
    const stop = Math.min(start + BATCH, this.frames);
    const bones = this.view.layers.bones;
    const body = {
      shape: Array.from({ length: stop - start }, () => this.shape),
      coordinates: this.coordinates.slice(start, stop),
      root: this.root.slice(start, stop),
      skeleton: bones,
      faces: bones && !this.synth.boneFaces,
    };
    const promise = postJSON("/v1/synthesize", body).then((buffer) => {
      const a = parseNpz(buffer);
      if (a.bone_faces) this.synth.boneFaces = a.bone_faces.data;
      const v = a.vertices.shape[1] * 3;
      const b = a.bones ? a.bones.shape[1] * 3 : 0;
      for (let f = start; f < stop; f++) {
        const i = f - start;
        this.bodies.set(f, {
          vertices: a.vertices.data.subarray(i * v, (i + 1) * v),
          bones: a.bones ? a.bones.data.subarray(i * b, (i + 1) * b) : null,
        });
      }
    });
    this.loading.set(batch, promise);
    promise.catch((error) => { this.loading.delete(batch); showError(error); });
    return promise;
  }

  async seek(frame) {
    this.current = Math.min(Math.max(frame, 0), this.frames - 1);
    if (!this.bodies.has(this.current)) await this.load(this.current);
    if (this.current + BATCH < this.frames) this.load(this.current + BATCH); // ahead of the playhead
    const body = this.bodies.get(this.current);
    this.view.setSkin(body.vertices, this.view.skin.geometry.index ? null : this.synth.faces);
    this.view.setBones(body.bones, body.bones && !this.view.bones.geometry.index ? this.synth.boneFaces : null);
    this.view.setJoints(this.joints[this.current], this.model.jointInfo);
    this.view.render();
    $("up-frame").value = this.current;
    $("up-time").textContent = `${this.current + 1} / ${this.frames} (${(this.current / this.rate).toFixed(2)} s)`;
    this.plot();
    this.values();
  }

  play() {
    if (!this.frames) return;
    this.playing = true;
    $("up-play").textContent = "❚❚";
    const began = performance.now() - (this.current / this.rate) * 1000;
    const tick = async () => {
      if (!this.playing) return;
      const frame = Math.floor(((performance.now() - began) / 1000) * this.rate) % this.frames;
      if (frame !== this.current) await this.seek(frame);
      this.played = (this.played || 0) + 1;
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  }

  pause() {
    this.playing = false;
    $("up-play").textContent = "▶";
  }

  chosen() {
    return Array.from($("up-coords").selectedOptions, (o) => o.value);
  }

  values() {
    const names = this.model.dofs.map((d) => d.name);
    $("up-values").innerHTML = this.chosen().map((name, k) => {
      const i = names.indexOf(name);
      const value = this.coordinates[this.current] ? this.coordinates[this.current][i] : NaN;
      return `<tr><td style="color:${COLOURS[k % COLOURS.length]}">${name}</td>
        <td data-dof="${name}">${formatValue(value, this.model.dofs[i].unit)}</td></tr>`;
    }).join("");
  }

  /** Each chosen coordinate over time (degrees for angles), a cursor at the current frame. */
  plot() {
    const canvas = $("up-plot");
    const g = canvas.getContext("2d");
    const { width: w, height: h } = canvas;
    g.clearRect(0, 0, w, h);
    if (!this.frames) return;
    const names = this.model.dofs.map((d) => d.name);
    const series = this.chosen().map((name) => {
      const i = names.indexOf(name);
      const scale = this.model.dofs[i].unit === "rad" ? DEG : 1;
      return this.coordinates.map((row) => row[i] * scale);
    });
    // a loop, not Math.min(...values): a long sequence's values would overflow the call's arguments
    let lo = 0;
    let hi = 1;
    for (const values of series) {
      for (const v of values) {
        if (v < lo) lo = v;
        if (v > hi) hi = v;
      }
    }
    const pad = 24;
    const x = (f) => pad + ((w - pad - 4) * f) / Math.max(this.frames - 1, 1);
    const y = (v) => h - 14 - ((h - 24) * (v - lo)) / (hi - lo);
    g.strokeStyle = "#d8dbe0";
    g.fillStyle = "#6a7380";
    g.font = "10px system-ui";
    for (const v of [lo, 0, hi]) {
      g.beginPath(); g.moveTo(pad, y(v)); g.lineTo(w - 4, y(v)); g.stroke();
      g.fillText(`${v.toFixed(0)}°`, 0, y(v) + 3);
    }
    g.fillText(`${(this.frames / this.rate).toFixed(2)} s`, w - 40, h - 2);
    series.forEach((values, k) => {
      g.strokeStyle = COLOURS[k % COLOURS.length];
      g.lineWidth = 1.5;
      g.beginPath();
      values.forEach((v, f) => (f ? g.lineTo(x(f), y(v)) : g.moveTo(x(f), y(v))));
      g.stroke();
    });
    g.strokeStyle = "#1d232b";
    g.lineWidth = 1;
    g.beginPath(); g.moveTo(x(this.current), 4); g.lineTo(x(this.current), h - 14); g.stroke();
  }
}
