// Anchoring: the photo beside a model view at the photo's date. A pair is a model point (server ray cast, snapped
// to a corner or edge) and the pixel showing it; from 4 pairs every change re-solves the pose on the server
// (POST /api/photos/ID/solve), shows each click's residual, flags mis-clicks and draws the model over the photo
// with the current solution. Submit posts the pairs (published as AnchorClicks in live mode).
import * as api from "./api.js";
import { marker, photoPixel } from "./draw.js";
import { ModelRenderer, OrbitView, project } from "./modelgl.js";

const $ = (s) => document.querySelector(s);

export class AnchorView {
  constructor(wb, say) {
    this.wb = wb;
    this.say = say;
    const canvas = $("#modelview");
    this.renderer = new ModelRenderer(canvas, wb.mesh, wb.model.elements);
    this.view = new OrbitView(canvas, this.renderer, wb.model.bbox_min_m, wb.model.bbox_max_m, (u, v, c) =>
      this.onModelClick(u, v, c),
    );
    this.view.afterDraw = () => this.drawModelMarkers();
    this.ghost = null;
    this.pairs = [];
    this.pendingWorld = null;
    this.pendingPixel = null;
    this.solution = null;
    this.state = "idle";
    $("#adraw").addEventListener("click", (e) => this.onPhotoClick(photoPixel($("#adraw"), e, this.photo)));
    $("#anchor-undo").onclick = () => this.removePair(this.pairs.length - 1);
    $("#anchor-clear").onclick = () => {
      this.pairs = [];
      this.pendingWorld = this.pendingPixel = null;
      this.update();
    };
    $("#anchor-ghost").onchange = () => this.drawGhost();
    $("#anchor-submit").onclick = () => this.submit();
  }

  async open(photoId) {
    const p = this.wb.byId[photoId];
    this.photo = p;
    this.photoId = photoId;
    this.pairs = [];
    this.pendingWorld = this.pendingPixel = null;
    this.solution = null;
    this.state = "picking";
    this.submitted = null;
    $("#anchor-title").textContent = `${p.filename} (${p.camera_id || "phone"}), ${p.status}`;
    $("#aphoto").src = api.photoUrl(photoId);
    $("#adraw").setAttribute("viewBox", `-0.5 -0.5 ${p.width_px} ${p.height_px}`);
    const ghost = $("#aover");
    ghost.width = p.width_px;
    ghost.height = p.height_px;
    const vis = await api.get(`/api/model/visible?at_ns=${p.capture_time}`);
    this.renderer.setVisible(vis.indices); // the model as it stood at the photo's date: future elements hidden
    if (!this.ghost) this.ghost = new ModelRenderer(ghost, this.wb.mesh, this.wb.model.elements);
    this.ghost.setVisible(vis.indices);
    this.view.draw();
    await this.update();
  }

  async onModelClick(u, v, camera) {
    const res = await api
      .send("POST", "/api/pick", { ...camera, u, v, at_ns: this.photo.capture_time, snap_px: 10 })
      .catch((e) => this.say(e.message));
    if (!res) return;
    if (!res.global_id) return this.say("no model surface under that point");
    const world = res.point_in_world_m;
    if (this.pendingPixel) {
      this.pairs.push({ world, pixel: this.pendingPixel, snapped: res.snapped, element: res.global_id });
      this.pendingPixel = null;
    } else this.pendingWorld = { world, snapped: res.snapped, element: res.global_id };
    await this.update();
  }

  async onPhotoClick(px) {
    if (this.pendingWorld) {
      this.pairs.push({ ...this.pendingWorld, pixel: px });
      this.pendingWorld = null;
    } else this.pendingPixel = px;
    await this.update();
  }

  async removePair(i) {
    if (i < 0) return;
    this.pairs.splice(i, 1);
    await this.update();
  }

  body() {
    return { points: this.pairs.map((q) => ({ pixel: q.pixel, world: q.world })) };
  }

  async update() {
    const gen = (this.generation = (this.generation || 0) + 1);
    let solution = null;
    if (this.pairs.length >= 4) {
      const t0 = performance.now();
      try {
        solution = await api.send("POST", `/api/photos/${this.photoId}/solve`, this.body());
        this.solveError = null;
      } catch (e) {
        this.solveError = e.message;
      }
      if (gen !== this.generation) return; // the pairs changed meanwhile: a newer update draws
      this.wb.timings.solveMs = performance.now() - t0;
    }
    this.solution = solution;
    this.renderTable();
    this.drawPhotoMarkers();
    this.view.draw();
    this.drawGhost();
  }

  renderTable() {
    const tb = $("#pairs tbody");
    tb.replaceChildren();
    const sol = this.solution;
    this.pairs.forEach((q, i) => {
      const tr = document.createElement("tr");
      const solved = sol && sol.residuals_px.length === this.pairs.length;
      const bad = solved && sol.misclick[i];
      tr.classList.toggle("misclick", !!bad);
      const res = solved ? sol.residuals_px[i].toFixed(1) : "";
      tr.innerHTML = `<td>${i + 1}</td><td>${q.world.map((x) => x.toFixed(2)).join(", ")} <small>${q.snapped}</small></td><td>${q.pixel.map((x) => x.toFixed(1)).join(", ")}</td><td class="residual">${res}${bad ? " mis-click?" : ""}</td>`;
      const td = document.createElement("td");
      const b = document.createElement("button");
      b.textContent = "remove";
      b.className = "remove-pair";
      b.onclick = () => this.removePair(i);
      td.append(b);
      tr.append(td);
      tb.append(tr);
    });
    if (this.pendingWorld || this.pendingPixel) {
      const tr = document.createElement("tr");
      tr.className = "pending";
      tr.innerHTML = this.pendingWorld ? `<td>${this.pairs.length + 1}</td><td colspan=4>model point picked: now click it in the photo</td>` : `<td>${this.pairs.length + 1}</td><td colspan=4>pixel picked: now click it on the model</td>`;
      tb.append(tr);
    }
    const info = $("#solve-info");
    const n = this.pairs.length;
    if (this.submitted) info.innerHTML = this.submitted;
    else if (sol) {
      const flagged = sol.misclick.filter(Boolean).length;
      info.innerHTML = `solved from ${n} clicks: RMS ${sol.rms_px.toFixed(2)} px, focal ${sol.intrinsics.f_px.toFixed(0)} px${sol.focal_solved ? " (solved)" : ""}${flagged ? `<br><b>${flagged} probable mis-click(s)</b> (red): remove or redo them` : ""}`;
      if (sol.note) {
        const note = document.createElement("div");
        note.className = "solve-note";
        note.textContent = sol.note; // e.g. the clicks also fit a camera turned elsewhere
        info.append(note);
      }
    } else info.textContent = this.solveError || `${n} of at least 4 pairs`;
    $("#anchor-submit").disabled = !sol || !!this.submittedPending;
  }

  drawPhotoMarkers() {
    const svg = $("#adraw");
    svg.replaceChildren();
    const s = Math.max(6, this.photo.width_px / 120);
    this.pairs.forEach((q, i) => {
      const bad = this.solution && this.solution.misclick[i];
      marker(svg, q.pixel[0], q.pixel[1], { color: bad ? "#ff1744" : "#ffeb3b", label: String(i + 1), size: s });
      if (this.solution) {
        const r = project(this.solution.world_from_camera, this.solution.intrinsics, q.world);
        if (r) marker(svg, r[0], r[1], { color: "#00e5ff", circle: true, size: s * 0.6 });
      }
    });
    if (this.pendingPixel) marker(svg, this.pendingPixel[0], this.pendingPixel[1], { color: "#ff9100", size: s });
  }

  drawModelMarkers() {
    const svg = $("#mdraw");
    svg.replaceChildren();
    const W = this.view.worldFromCamera(), K = this.view.intrinsics();
    const items = this.pairs.map((q, i) => [q.world, String(i + 1), "#d50000"]);
    if (this.pendingWorld) items.push([this.pendingWorld.world, "?", "#ff6d00"]);
    for (const [w, label, color] of items) {
      const r = project(W, K, w);
      if (r) marker(svg, r[0], r[1], { color, label, size: 7 });
    }
  }

  drawGhost() {
    if (!this.ghost) return;
    const sol = this.solution;
    const c = $("#aover");
    if (!sol || !$("#anchor-ghost").checked) {
      this.ghost.gl.clearColor(0, 0, 0, 0);
      this.ghost.gl.clear(this.ghost.gl.COLOR_BUFFER_BIT);
      c.dataset.drawn = "0";
      return;
    }
    this.ghost.draw(sol.world_from_camera, sol.intrinsics, { alpha: 0.35, clear: [0, 0, 0, 0] });
    c.dataset.drawn = "1";
  }

  async submit() {
    const body = { ...this.body(), author: "workbench" };
    const res = await api.send("POST", `/api/photos/${this.photoId}/anchors`, body).catch((e) => this.say(e.message));
    if (!res) return;
    this.submittedPending = true;
    this.submitted = res.published
      ? `submitted ${this.pairs.length} clicks (RMS ${res.rms_px.toFixed(2)} px): waiting for the registration...`
      : `solved (RMS ${res.rms_px.toFixed(2)} px); review mode: nothing was published`;
    this.state = res.published ? "submitted" : "solved";
    this.renderTable();
    this.refreshStatus();
  }

  refreshStatus() {
    if (!this.photoId || !this.submittedPending) return;
    const p = this.wb.byId[this.photoId];
    if (p && (p.status === "anchor" || p.status === "auto")) {
      this.state = "registered";
      this.submitted = `registered (${p.status}, ${p.method}): ${p.num_inliers} inliers, RMS ${(p.reprojection_rms_px || 0).toFixed(2)} px`;
      $("#anchor-title").textContent = `${p.filename} (${p.camera_id || "phone"}), ${p.status}`;
      this.renderTable();
    }
  }
}
