// Workbench page: site view (cameras, timeline, overlays, masks), selection, annotations, time slider and peeks.
// State for people and tests lives in window.wb (read-only for tests: they act through the page).
import * as api from "./api.js";
import { AnchorView } from "./anchor.js";
import { parseMesh } from "./modelgl.js";
import { drawPolygons, photoPixel, svgEl } from "./draw.js";
import { ProgressPanel } from "./progress.js";

const $ = (s) => document.querySelector(s);
const wb = (window.wb = {
  ready: false,
  photos: [],
  byId: {},
  group: null,
  current: null,
  selection: { element_ids: [], elements: [], polygons: [], region_polygons: [] },
  region: null,
  annotations: [],
  lastPeek: null,
  overlayMode: null,
  maskKind: null,
  tool: "select",
  timings: {},
  editing: null,
});

export function say(text) {
  $("#message").textContent = text;
}

function fmtTime(ns, tz) {
  return new Date(ns / 1e6).toLocaleString("en-GB", { timeZone: tz || "UTC", dateStyle: "medium", timeStyle: "short" });
}

function groupOf(p) {
  if (p.camera_id) return p.camera_id;
  const day = new Date(p.capture_time / 1e6).toLocaleDateString("en-CA", { timeZone: p.tz || "UTC" });
  return `phone ${day}`;
}

async function loadPhotos() {
  wb.photos = await api.get("/api/photos");
  wb.byId = Object.fromEntries(wb.photos.map((p) => [p.photo_id, p]));
  const groups = new Map();
  for (const p of wb.photos) {
    const g = groupOf(p);
    if (!groups.has(g)) groups.set(g, []);
    groups.get(g).push(p);
  }
  wb.groups = groups;
  const ul = $("#cameras");
  ul.replaceChildren();
  for (const [g, list] of groups) {
    const li = document.createElement("li");
    const reg = list.filter((p) => p.status === "anchor" || p.status === "auto").length;
    li.textContent = `${g} (${reg}/${list.length} registered)`;
    li.dataset.group = g;
    li.classList.toggle("active", g === wb.group);
    li.onclick = () => showGroup(g);
    ul.append(li);
  }
  const queue = await api.get("/api/anchor-queue");
  wb.queue = queue;
  $("#queue-count").textContent = queue.length;
  const q = $("#queue");
  q.replaceChildren();
  for (const item of queue) {
    const li = document.createElement("li");
    li.dataset.photo = item.photo_id;
    li.textContent = `${item.filename || item.photo_id}: ${item.reason}`;
    li.onclick = () => openAnchor(item.photo_id);
    q.append(li);
  }
  if (wb.group) renderTimeline();
}

function showGroup(g, pick = "last") {
  wb.group = g;
  for (const li of $("#cameras").children) li.classList.toggle("active", li.dataset.group === g);
  renderTimeline();
  const list = wb.groups.get(g) || [];
  if (list.length) showPhoto((pick === "last" ? list[list.length - 1] : list[0]).photo_id);
}

function renderTimeline() {
  const tl = $("#timeline");
  tl.replaceChildren();
  for (const p of wb.groups.get(wb.group) || []) {
    const fig = document.createElement("figure");
    fig.dataset.photo = p.photo_id;
    fig.classList.toggle("current", p.photo_id === wb.current);
    const q = p.reprojection_rms_px != null && p.status !== "failed" ? `, ${p.num_inliers} inl, ${p.reprojection_rms_px.toFixed(2)} px` : "";
    fig.title = `${p.filename}: ${p.status}${q}${p.message ? " - " + p.message : ""}`;
    const img = document.createElement("img");
    img.loading = "lazy";
    img.src = api.thumbUrl(p.photo_id);
    const cap = document.createElement("figcaption");
    cap.innerHTML = `<span class="st st-${p.status}">${p.status}</span> ${fmtTime(p.capture_time, p.tz)}`;
    fig.append(img, cap);
    fig.onclick = () => showPhoto(p.photo_id);
    tl.append(fig);
  }
}

export async function showPhoto(id) {
  const p = wb.byId[id];
  if (!p) return;
  const changed = wb.current !== id;
  wb.current = id;
  if (groupOf(p) !== wb.group) {
    wb.group = groupOf(p);
    for (const li of $("#cameras").children) li.classList.toggle("active", li.dataset.group === wb.group);
    renderTimeline();
  }
  for (const f of $("#timeline").children) f.classList.toggle("current", f.dataset.photo === id);
  const svg = $("#draw");
  svg.setAttribute("viewBox", `-0.5 -0.5 ${p.width_px} ${p.height_px}`);
  if (changed) {
    $("#photo").src = api.photoUrl(id);
    $("#peekimg").removeAttribute("src");
    $("#peek-info").textContent = "";
    wb.lastPeek = null;
  }
  setTimeValue(p.capture_time);
  renderModes(p);
  renderInfo(p);
  if (changed) wb.highlight = [];
  await Promise.all([loadAnnotations(), refreshSelectionOutline(), progressPanel.load(id)]);
  if (wb.region && $("#peek-toggle").checked && !changed) await peek();
  drawAll();
}

function renderModes(p) {
  const modes = $("#overlay-modes");
  modes.replaceChildren();
  if (!p.overlays.includes(wb.overlayMode)) wb.overlayMode = null;
  for (const m of ["none", ...p.overlays]) {
    const b = document.createElement("button");
    b.textContent = m;
    b.dataset.mode = m;
    b.classList.toggle("on", (wb.overlayMode || "none") === m);
    b.onclick = () => setOverlay(m === "none" ? null : m);
    modes.append(b);
  }
  setOverlay(wb.overlayMode, true);
  const masks = $("#mask-kinds");
  masks.replaceChildren();
  if (!p.masks.includes(wb.maskKind)) wb.maskKind = null;
  for (const k of p.masks) {
    const b = document.createElement("button");
    b.textContent = `mask ${k}`;
    b.dataset.mask = k;
    b.classList.toggle("on", wb.maskKind === k);
    b.onclick = () => {
      wb.maskKind = wb.maskKind === k ? null : k;
      renderModes(wb.byId[wb.current]);
    };
    masks.append(b);
  }
  const mi = $("#maskimg");
  if (wb.maskKind) mi.src = api.maskUrl(p.photo_id, wb.maskKind);
  else mi.removeAttribute("src");
}

function setOverlay(mode, quiet = false) {
  const img = $("#overlay");
  wb.overlayMode = mode;
  for (const b of $("#overlay-modes").children) b.classList.toggle("on", (mode || "none") === b.dataset.mode);
  if (!mode) {
    img.removeAttribute("src");
    wb.timings.overlayShown = mode;
    return;
  }
  const t0 = performance.now();
  const src = api.overlayUrl(wb.current, mode);
  img.onload = () => {
    wb.timings.overlaySwitchMs = performance.now() - t0;
    wb.timings.overlayShown = mode;
  };
  if (!quiet || img.getAttribute("src") !== src) img.src = src;
}

function renderInfo(p) {
  const rows = [
    ["file", p.filename],
    ["camera", p.camera_id || "phone"],
    ["taken", fmtTime(p.capture_time, p.tz)],
    ["status", `<span class="st st-${p.status}">${p.status}</span>`],
  ];
  if (p.status === "anchor" || p.status === "auto") {
    rows.push(["method", p.method], ["inliers", p.num_inliers], ["RMS", `${(p.reprojection_rms_px || 0).toFixed(2)} px`]);
    if (p.anchor_residuals_px.length) rows.push(["anchor clicks", p.anchor_residuals_px.map((r) => r.toFixed(1)).join(", ") + " px"]);
  }
  if (p.needs_anchor_reason) rows.push(["asks", p.needs_anchor_reason]);
  if (p.message) rows.push(["note", p.message]);
  $("#photo-info").innerHTML = "<dl>" + rows.map(([k, v]) => `<dt>${k}</dt><dd>${v}</dd>`).join("") + "</dl>";
}

// -- drawing on the photo -------------------------------------------------------------------------------------

function drawAll() {
  const svg = $("#draw");
  svg.replaceChildren();
  for (const a of wb.annotations) {
    const [r, g, b, al] = a.rgba;
    drawPolygons(svg, a.polygons, { fill: `rgba(${r},${g},${b},${(al / 255).toFixed(2)})`, stroke: `rgb(${r},${g},${b})`, cls: "annotation", data: { annotation: a.annotation_id } });
  }
  drawPolygons(svg, wb.selection.polygons, { fill: "rgba(77,124,254,0.25)", stroke: "#4d7cfe", cls: "selection" });
  drawPolygons(svg, wb.highlight, { fill: "rgba(255,213,79,0.3)", stroke: "#ffb300", cls: "detection" });
  drawPolygons(svg, wb.selection.region_polygons, { fill: "rgba(255,255,255,0.15)", stroke: "#fff", dash: true, cls: "region" });
  if (wb.region) drawPolygons(svg, [wb.region], { fill: "none", stroke: "#ffeb3b", dash: true, cls: "peek-region" });
  if (wb.drawing && wb.drawing.length) {
    const pts = wb.drawing.map((q) => q.join(",")).join(" ");
    svg.append(svgEl("polyline", { points: pts, fill: "none", stroke: "#ffeb3b", "stroke-width": 2, "vector-effect": "non-scaling-stroke" }));
  }
}

async function loadAnnotations() {
  const p = wb.byId[wb.current];
  const list = await api.get(`/api/annotations?photo_id=${p.photo_id}`);
  if (wb.current !== p.photo_id) return; // moved on meanwhile
  wb.annotations = list;
  wb.annotationsFor = p.photo_id;
  const ul = $("#annotations");
  ul.replaceChildren();
  for (const a of wb.annotations) {
    const li = document.createElement("li");
    li.dataset.annotation = a.annotation_id;
    li.style.borderColor = `rgb(${a.rgba.slice(0, 3).join(",")})`;
    const what = a.element_ids.length ? `${a.element_ids.length} element(s)` : "region";
    li.innerHTML = `<b>${a.status || a.kind}</b> ${a.text ? "- " + a.text : ""}<br><small>${what}, rev ${a.revision}${a.photo_id === p.photo_id ? "" : ", transferred"}</small> `;
    for (const [label, fn] of [["edit", () => editAnnotation(a)], ["delete", () => deleteAnnotation(a)], ["history", () => showHistory(a, li)]]) {
      const b = document.createElement("button");
      b.textContent = label;
      b.className = `ann-${label}`;
      b.onclick = fn;
      li.append(b);
    }
    ul.append(li);
  }
  drawAll();
}

function editAnnotation(a) {
  wb.editing = a.annotation_id;
  $("#ann-status").value = a.status;
  $("#ann-text").value = a.text;
  $("#ann-color").value = "#" + a.rgba.slice(0, 3).map((c) => c.toString(16).padStart(2, "0")).join("");
  $("#ann-save").textContent = "save changes";
}

async function deleteAnnotation(a) {
  await guarded(async () => {
    await api.send("DELETE", `/api/annotations/${a.annotation_id}`);
    await loadAnnotations();
  });
}

async function showHistory(a, li) {
  const revs = await api.get(`/api/annotations/${a.annotation_id}/history`);
  const pre = document.createElement("ol");
  pre.className = "history";
  for (const r of revs) {
    const item = document.createElement("li");
    item.textContent = `rev ${r.revision}: ${r.deleted ? "deleted" : (r.status || r.kind) + (r.text ? " - " + r.text : "")} (${new Date(r.modified_ns / 1e6).toLocaleString()})`;
    pre.append(item);
  }
  li.append(pre);
}

async function saveAnnotation(e) {
  e.preventDefault();
  const hex = $("#ann-color").value;
  const rgb = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
  const body = { status: $("#ann-status").value, text: $("#ann-text").value, rgba: [...rgb, 150], author: "workbench" };
  await guarded(async () => {
    if (wb.editing) {
      await api.send("PUT", `/api/annotations/${wb.editing}`, body);
      wb.editing = null;
      $("#ann-save").textContent = "annotate selection";
    } else {
      body.photo_id = wb.current;
      if (wb.selection.element_ids.length) body.element_ids = wb.selection.element_ids;
      else if (wb.selection.region_polygons.length) body.polygon_px = wb.selection.region_polygons[0];
      else if (wb.region) body.polygon_px = wb.region;
      else throw new Error("select elements or draw a region first");
      if (wb.maskKind && !body.element_ids && wb.lastTool === "occlusion") body.kind = "occluder";
      await api.send("POST", "/api/annotations", body);
    }
    say("annotation saved");
    await loadAnnotations();
  });
}

// -- selection tools --------------------------------------------------------------------------------------------

async function guarded(fn) {
  try {
    return await fn();
  } catch (err) {
    say(err.message);
    return undefined;
  }
}

async function select(body, add = false) {
  const out = await guarded(() => api.send("POST", `/api/photos/${wb.current}/select`, body));
  if (!out) return;
  wb.lastTool = body.mode;
  if (add && out.element_ids.length) {
    const ids = [...new Set([...wb.selection.element_ids, ...out.element_ids])];
    const more = await api.get(`/api/photos/${wb.current}/outline?element_ids=${ids.join(",")}`).catch(() => null);
    out.element_ids = ids;
    out.elements = [...wb.selection.elements, ...out.elements.filter((e) => !wb.selection.element_ids.includes(e.global_id))];
    out.polygons = more ? more.polygons : [...wb.selection.polygons, ...out.polygons];
  }
  if (body.mode === "region" || body.mode === "occlusion") wb.region = out.region_polygons[0] || null;
  setSelection(out);
}

function setSelection(out) {
  wb.selection = out;
  const ul = $("#selection");
  ul.replaceChildren();
  for (const e of out.elements) {
    const li = document.createElement("li");
    li.dataset.element = e.global_id;
    const tasks = e.tasks.map((t) => t.name).join(", ");
    li.innerHTML = `<b>${e.ifc_class}</b> ${e.name || ""}<br>${e.global_id}<br>${e.storey} · ${e.material || "-"} · ${e.type_name || "-"}<br><small>${tasks}${e.planned_state ? " · " + e.planned_state : ""}</small>`;
    ul.append(li);
  }
  if (!out.elements.length && out.region_polygons.length) ul.innerHTML = "<li>pixel region</li>";
  drawAll();
}

async function refreshSelectionOutline() {
  const p = wb.byId[wb.current];
  if (!wb.selection.element_ids.length) return;
  if (p.status !== "anchor" && p.status !== "auto") {
    wb.selection = { ...wb.selection, polygons: [] };
    return;
  }
  const out = await guarded(() => api.get(`/api/photos/${p.photo_id}/outline?element_ids=${wb.selection.element_ids.join(",")}`));
  if (out) wb.selection = { ...wb.selection, polygons: out.polygons, region_polygons: [] };
}

function bindTools() {
  for (const b of document.querySelectorAll("#tools .tool"))
    b.onclick = () => {
      wb.tool = b.dataset.tool;
      wb.drawing = null;
      for (const o of document.querySelectorAll("#tools .tool")) o.classList.toggle("active", o === b);
    };
  const svg = $("#draw");
  let down = false;
  svg.addEventListener("pointerdown", (e) => {
    const p = wb.byId[wb.current];
    const px = photoPixel(svg, e, p);
    if (["lasso", "brush", "rect"].includes(wb.tool)) {
      down = true;
      wb.drawing = [px];
      svg.setPointerCapture(e.pointerId);
    }
  });
  svg.addEventListener("pointermove", (e) => {
    if (!down) return;
    const px = photoPixel(svg, e, wb.byId[wb.current]);
    if (wb.tool === "rect") {
      const a = wb.drawing[0];
      wb.drawing = [a, [px[0], a[1]], px, [a[0], px[1]], a];
    } else wb.drawing.push(px);
    drawAll();
  });
  svg.addEventListener("pointerup", async (e) => {
    const p = wb.byId[wb.current];
    const px = photoPixel(svg, e, p);
    if (down) {
      down = false;
      const pts = wb.drawing || [];
      wb.drawing = null;
      if (wb.tool === "lasso" && pts.length >= 3) await select({ mode: "region", polygon: pts });
      if (wb.tool === "brush") await select({ mode: "region", brush: pts, radius_px: Math.max(6, p.width_px / 80) });
      if (wb.tool === "rect" && pts.length >= 4) {
        wb.region = pts.slice(0, 4);
        if ($("#peek-toggle").checked) await peek();
      }
      drawAll();
      return;
    }
    if (wb.tool === "select") await select({ mode: "click", u: px[0], v: px[1] }, e.shiftKey);
    if (wb.tool === "occlusion") {
      const kind = ["combined", "static", "dynamic", "user"].find((k) => p.masks.includes(k));
      if (!kind) return say("this photo has no occlusion mask");
      await select({ mode: "occlusion", u: px[0], v: px[1], kind });
    }
    if (wb.tool === "polygon") {
      wb.drawing = [...(wb.polygonDraft || []), px];
      wb.polygonDraft = wb.drawing;
      drawAll();
    }
  });
  svg.addEventListener("dblclick", async () => {
    if (wb.tool !== "polygon" || !wb.polygonDraft || wb.polygonDraft.length < 3) return;
    const pts = wb.polygonDraft;
    wb.polygonDraft = null;
    wb.drawing = null;
    await select({ mode: "region", polygon: pts });
  });
  for (const b of document.querySelectorAll("#grow [data-by]"))
    b.onclick = () => select({ mode: "grow", element_ids: wb.selection.element_ids, by: b.dataset.by });
  $("#clear-selection").onclick = () => {
    wb.region = null;
    setSelection({ element_ids: [], elements: [], polygons: [], region_polygons: [] });
  };
  $("#annotate").addEventListener("submit", saveAnnotation);
  $("#preview-btn").onclick = () =>
    guarded(async () => {
      if (!wb.selection.element_ids.length) throw new Error("select elements first");
      const url = `/api/photos/${wb.current}/preview?element_ids=${wb.selection.element_ids.join(",")}`;
      const resp = await fetch(url);
      if (!resp.ok) throw new Error((await resp.json()).error);
      $("#peekimg").src = URL.createObjectURL(await resp.blob());
      $("#peek-info").textContent = "photoreal preview of the selection";
    });
  $("#reanchor").onclick = () => openAnchor(wb.current);
  $("#peek-toggle").onchange = async () => {
    if ($("#peek-toggle").checked) {
      if (wb.region) await peek();
      else say("draw a region (region tool) to peek into");
    } else {
      $("#peekimg").removeAttribute("src");
      $("#peek-info").textContent = "";
      wb.lastPeek = null;
    }
  };
}

// -- time ---------------------------------------------------------------------------------------------------------

function setupTime() {
  const times = wb.photos.map((p) => p.capture_time);
  const range = wb.model ? wb.model.time_range_ns : [Math.min(...times), Math.max(...times)];
  const slider = $("#time");
  slider.min = Math.floor(range[0] / 1e9);
  slider.max = Math.ceil(range[1] / 1e9);
  slider.step = 600;
  slider.oninput = () => onTime(Number(slider.value) * 1e9, false);
  slider.onchange = () => onTime(Number(slider.value) * 1e9, true);
}

function setTimeValue(ns) {
  $("#time").value = Math.round(ns / 1e9);
  const p = wb.byId[wb.current];
  $("#time-label").textContent = fmtTime(ns, p && p.tz);
}

async function onTime(ns, final) {
  const p = wb.byId[wb.current];
  $("#time-label").textContent = fmtTime(ns, p && p.tz);
  if ($("#peek-toggle").checked && wb.region) {
    if (final) await peek(ns);
    return;
  }
  const list = wb.groups.get(wb.group) || [];
  let best = null;
  for (const q of list) if (!best || Math.abs(q.capture_time - ns) < Math.abs(best.capture_time - ns)) best = q;
  if (best && best.photo_id !== wb.current) await showPhoto(best.photo_id);
  if (final) setTimeValue(ns);
}

async function peek(ns) {
  const at = ns ?? Number($("#time").value) * 1e9;
  const seq = (wb.peekSeq = (wb.peekSeq || 0) + 1);
  if (Math.abs(at - wb.byId[wb.current].capture_time) < 600e9) {
    // the slider is at the photo's own time (within its 10 min step): nothing to peek at
    $("#peekimg").removeAttribute("src");
    $("#peek-info").textContent = "move the slider to look back or ahead";
    wb.lastPeek = null;
    return;
  }
  const res = await guarded(() => api.postForImage(`/api/photos/${wb.current}/peek`, { at_ns: at, polygon: wb.region }));
  if (!res || seq !== wb.peekSeq) return; // a newer peek was asked for meanwhile
  $("#peekimg").src = res.url;
  wb.lastPeek = res.meta;
  const src = res.meta.source_photo_id && wb.byId[res.meta.source_photo_id];
  $("#peek-info").textContent =
    res.meta.direction === "backward" ? `peek back: ${src ? src.filename : res.meta.source_photo_id}` : `peek forward: model at ${fmtTime(at)}`;
}

// -- anchoring ----------------------------------------------------------------------------------------------------

let anchorView = null;

async function openAnchor(photoId) {
  if (!wb.mesh) return say("no model yet");
  $("#site-view").hidden = true;
  $("#anchor-view").hidden = false;
  $("#tab-site").classList.remove("active");
  $("#tab-anchor").classList.add("active");
  if (!anchorView) anchorView = wb.anchor = new AnchorView(wb, say);
  await anchorView.open(photoId);
}

function showSite() {
  $("#site-view").hidden = false;
  $("#anchor-view").hidden = true;
  $("#tab-site").classList.add("active");
  $("#tab-anchor").classList.remove("active");
}

// -- live updates ---------------------------------------------------------------------------------------------------

const progressPanel = new ProgressPanel(wb, {
  say,
  redraw: () => drawAll(),
  onReviewed: () => loadAnnotations(),
  show: (id) => showPhoto(id),
});

let reloadTimer = null;
function onEvent(ev) {
  wb.lastEvent = ev;
  if (["photo", "registration", "needs_anchor", "overlay", "occlusion"].includes(ev.kind)) {
    clearTimeout(reloadTimer);
    reloadTimer = setTimeout(async () => {
      await loadPhotos();
      if (!wb.current && wb.photos.length) showGroup(groupOf(wb.photos[0]));
      else if (wb.current) {
        const p = wb.byId[wb.current];
        renderModes(p);
        renderInfo(p);
      }
      if (anchorView) anchorView.refreshStatus();
    }, 150);
  }
  if (ev.kind === "annotation" && wb.current) loadAnnotations();
  if (["evidence", "progress", "annotation"].includes(ev.kind) && wb.current) progressPanel.refreshSoon();
  if (ev.kind === "model") loadModel().then(setupTime);
}

async function loadModel() {
  try {
    wb.model = await api.get("/api/model");
    wb.mesh = parseMesh(await api.getBytes("/api/model/mesh.bin"));
  } catch (err) {
    say(err.message);
  }
}

async function init() {
  const site = await api.get("/api/site");
  $("#site-name").textContent = site.site;
  const badge = $("#mode-badge");
  badge.textContent = site.live ? "live" : "review (nothing is published)";
  badge.classList.toggle("review", !site.live);
  await loadModel();
  await loadPhotos();
  setupTime();
  bindTools();
  $("#tab-site").onclick = showSite;
  $("#tab-anchor").onclick = () => (wb.queue.length ? openAnchor(wb.queue[0].photo_id) : say("no anchor requests"));
  api.events(onEvent, (on) => $("#live-dot").classList.toggle("on", on));
  await progressPanel.loadQueue();
  const first = wb.photos.filter((p) => p.camera_id && (p.status === "anchor" || p.status === "auto"));
  if (wb.photos.length) await showGroup(groupOf(first.length ? first[first.length - 1] : wb.photos[0]));
  wb.showSite = showSite;
  wb.ready = true;
  document.body.dataset.ready = "1";
}

init().catch((err) => say(`cannot start: ${err.message}`));
