// Progress panel: what the progress node read of each element in the current photo, and a person's review of it.
// A review (confirm, or say built / not built) becomes a status annotation that the progress node takes as evidence.
import * as api from "./api.js";

const $ = (s) => document.querySelector(s);
const pct = (x) => `${Math.round(100 * x)}%`;
const words = (s) => (s || "").replace("_", " ");
const REVIEWABLE = ["built", "not_built"];

export class ProgressPanel {
  constructor(wb, { say, redraw, onReviewed, show }) {
    this.wb = wb;
    this.show = show;
    this.say = say;
    this.redraw = redraw;
    this.onReviewed = onReviewed;
    this.timer = null;
    wb.detections = null;
    wb.highlight = [];
    wb.reviewQueue = [];
  }

  // Reload soon (events come in bursts: one ProgressUpdate per photo read).
  refreshSoon() {
    clearTimeout(this.timer);
    this.timer = setTimeout(() => {
      this.loadQueue();
      if (this.wb.current) this.load(this.wb.current);
    }, 250);
  }

  // Readings that disagree with the plan (built before its start, not built after its finish), farthest off first.
  async loadQueue() {
    let items;
    try {
      items = await api.get("/api/progress/review-queue?limit=30");
    } catch (err) {
      return; // no model yet
    }
    this.wb.reviewQueue = items;
    $("#rq-count").textContent = items.length;
    const ul = $("#review-queue");
    ul.replaceChildren();
    for (const q of items) {
      const li = document.createElement("li");
      li.dataset.photo = q.photo_id;
      li.dataset.element = q.global_id;
      const side = q.reading === "built" ? "before its planned start" : "after its planned finish";
      li.innerHTML = `<b>${q.name || q.global_id}</b> read ${words(q.reading)} ${q.days_off.toFixed(1)} d ${side}<br><small>${q.camera_id || "phone"}</small>`;
      li.onclick = async () => {
        await this.show(q.photo_id);
        await this.highlight(q.photo_id, q.global_id);
      };
      ul.append(li);
    }
  }

  async load(photoId) {
    const ul = $("#detections");
    let doc;
    try {
      doc = await api.get(`/api/photos/${photoId}/progress`);
    } catch (err) {
      if (this.wb.current !== photoId) return;
      this.wb.detections = null;
      $("#detect-summary").textContent = err.status === 404 ? "no progress reading of this photo yet" : err.message;
      ul.replaceChildren();
      return;
    }
    if (this.wb.current !== photoId) return; // moved on meanwhile
    this.wb.detections = doc;
    const count = (s) => doc.elements.filter((e) => e.photo.state === s).length;
    const deviating = doc.elements.filter((e) => e.fused && ["behind", "ahead", "not_built"].includes(e.fused.deviation));
    $("#detect-summary").textContent =
      `${count("built")} built, ${count("not_built")} not built, ${count("occluded")} occluded, ${count("unknown")} unknown` +
      (deviating.length ? `; ${deviating.length} off schedule` : "");
    ul.replaceChildren();
    // Occluded ones are hidden in the photo (a person cannot tell either); unknown ones a person can often answer.
    for (const e of doc.elements.filter((x) => x.photo.state !== "occluded" || x.review)) ul.append(this.row(photoId, e));
  }

  row(photoId, e) {
    const li = document.createElement("li");
    li.dataset.element = e.global_id;
    li.dataset.state = e.photo.state;
    const fused = e.fused
      ? `now ${words(e.fused.state)}, <span class="dev dev-${e.fused.deviation}">${words(e.fused.deviation)}</span>`
      : "not fused yet";
    const review = e.review ? `<br><small class="reviewed">reviewed: ${words(e.review.status)}${e.review.author ? " by " + e.review.author : ""}</small>` : "";
    li.innerHTML =
      `<a href="#" class="det-name">${e.name || e.global_id}</a> <small>${e.ifc_class}</small><br>` +
      `<span class="det det-${e.photo.state}" title="read in this photo">${words(e.photo.state)} ${pct(e.photo.confidence)}</span> ` +
      `<small title="${e.fused ? "P(stands) " + e.fused.present_probability.toFixed(2) + " at the latest photo" : ""}">${fused}</small>${review}<br>`;
    li.querySelector(".det-name").onclick = (ev) => {
      ev.preventDefault();
      this.highlight(photoId, e.global_id);
    };
    for (const [verdict, label] of [["confirm", "✓ right"], ["built", "built"], ["not_built", "not built"]]) {
      const b = document.createElement("button");
      b.textContent = label;
      b.className = `review-${verdict}`;
      b.title = verdict === "confirm" ? "the reading is right" : `the element is ${words(verdict)} in this photo`;
      b.disabled = verdict === "confirm" && !REVIEWABLE.includes(e.photo.state);
      b.onclick = () => this.review(photoId, e, verdict);
      li.append(b);
    }
    return li;
  }

  async highlight(photoId, gid) {
    try {
      const out = await api.get(`/api/photos/${photoId}/outline?element_ids=${encodeURIComponent(gid)}`);
      if (this.wb.current !== photoId) return;
      this.wb.highlight = out.polygons;
      this.wb.highlighted = gid;
      this.redraw();
    } catch (err) {
      this.say(err.message);
    }
  }

  async review(photoId, e, verdict) {
    try {
      const ann = await api.send("POST", `/api/photos/${photoId}/progress/review`, { global_id: e.global_id, verdict, author: "workbench" });
      this.say(`${e.name || e.global_id}: ${ann.text}`);
      await this.onReviewed();
      await this.load(photoId);
    } catch (err) {
      this.say(err.message);
    }
  }
}
