// SVG helpers: the photo's SVG layer uses viewBox "-0.5 -0.5 W H", so its user units are OpenCV photo pixels.
const NS = "http://www.w3.org/2000/svg";

export function svgEl(tag, attrs) {
  const el = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
  return el;
}

// Photo pixel (u, v), OpenCV convention, of a pointer event on an element covering the whole photo.
export function photoPixel(el, e, photo) {
  const r = el.getBoundingClientRect();
  return [((e.clientX - r.left) * photo.width_px) / r.width - 0.5, ((e.clientY - r.top) * photo.height_px) / r.height - 0.5];
}

export function drawPolygons(svg, polygons, { fill, stroke, dash = false, cls = "", data = {} }) {
  for (const poly of polygons || []) {
    if (!poly || poly.length < 2) continue;
    const el = svgEl("polygon", {
      points: poly.map((q) => `${q[0]},${q[1]}`).join(" "),
      fill,
      stroke,
      "stroke-width": 2,
      "vector-effect": "non-scaling-stroke",
      class: cls,
    });
    if (dash) el.setAttribute("stroke-dasharray", "6 4");
    for (const [k, v] of Object.entries(data)) el.dataset[k] = v;
    svg.append(el);
  }
}

export function marker(svg, u, v, { color = "#ffeb3b", label = "", size = 8, circle = false } = {}) {
  if (circle) svg.append(svgEl("circle", { cx: u, cy: v, r: size, fill: "none", stroke: color, "stroke-width": 2, "vector-effect": "non-scaling-stroke" }));
  else {
    svg.append(svgEl("path", { d: `M${u - size},${v}H${u + size}M${u},${v - size}V${v + size}`, stroke: color, "stroke-width": 2, "vector-effect": "non-scaling-stroke" }));
  }
  if (label) {
    const t = svgEl("text", { x: u + size, y: v - size, fill: color, "font-size": size * 2.2, "paint-order": "stroke", stroke: "#000", "stroke-width": 3 });
    t.textContent = label;
    svg.append(t);
  }
}
