// WebGL2 drawing of the BIM (triangles shaded by IFC-class colour, feature edges) for an OpenCV pinhole camera,
// and the orbit / pan / zoom model view. Cameras: worldFromCamera is a row-major 4x4 (OpenCV frame: x right,
// y down, z forward), intrinsics {width_px, height_px, f_px, cx_px, cy_px} with pixel (0, 0) at the centre of the
// top-left pixel. Picking is the server's ray cast (POST /api/pick): this module only draws.

const VERT = `#version 300 es
in vec3 position; in vec3 normal; in float owner;
uniform mat4 clipFromWorld; uniform sampler2D table; uniform float edgePass;
out vec4 vColor;
void main() {
  int i = int(owner + 0.5);
  vec4 t = texelFetch(table, ivec2(i % 2048, i / 2048), 0);
  float shade = 0.45 + 0.55 * abs(dot(normalize(normal), normalize(vec3(0.35, -0.55, 0.76))));
  vec3 rgb = edgePass > 0.5 ? vec3(0.08) : t.rgb * shade;
  vColor = vec4(rgb, 1.0);
  gl_Position = t.a < 0.5 ? vec4(2.0, 2.0, 2.0, 1.0) : clipFromWorld * vec4(position, 1.0);
}`;
const FRAG = `#version 300 es
precision highp float; in vec4 vColor; uniform float alpha; out vec4 outColor;
void main() { outColor = vec4(vColor.rgb, alpha); }`;

export function classColor(name) {
  let h = 2166136261;
  for (const c of name) h = Math.imul(h ^ c.charCodeAt(0), 16777619) >>> 0;
  const hue = (h % 360) / 360;
  const f = (n) => {
    const k = (n + hue * 12) % 12;
    return 0.62 - 0.4 * Math.max(-1, Math.min(k - 3, 9 - k, 1));
  };
  return [f(0), f(8), f(4)];
}

export function parseMesh(buf) {
  const head = new Uint32Array(buf, 0, 2);
  const [T, K] = head;
  let off = 8;
  const tri = new Float32Array(buf, off, T * 9);
  off += T * 36;
  const triOwner = new Uint32Array(buf, off, T);
  off += T * 4;
  const edges = new Float32Array(buf, off, K * 6);
  off += K * 24;
  const edgeOwner = new Uint32Array(buf, off, K);
  return { T, K, tri, triOwner, edges, edgeOwner };
}

// clip_from_world of an OpenCV camera: x_ndc = 2 (u + 0.5) / w - 1, y_ndc = 1 - 2 (v + 0.5) / h.
export function clipFromWorld(worldFromCamera, intr, near, far) {
  const W = worldFromCamera;
  const R = [W[0], W[1], W[2], W[4], W[5], W[6], W[8], W[9], W[10]];
  const t = [W[3], W[7], W[11]];
  // camera_from_world = [R^T | -R^T t]
  const C = [
    R[0], R[3], R[6], -(R[0] * t[0] + R[3] * t[1] + R[6] * t[2]),
    R[1], R[4], R[7], -(R[1] * t[0] + R[4] * t[1] + R[7] * t[2]),
    R[2], R[5], R[8], -(R[2] * t[0] + R[5] * t[1] + R[8] * t[2]),
    0, 0, 0, 1,
  ];
  const w = intr.width_px, h = intr.height_px, fx = intr.f_px, fy = intr.f_px * (intr.fy_over_fx || 1);
  const P = [
    (2 * fx) / w, 0, (2 * (intr.cx_px + 0.5)) / w - 1, 0,
    0, (-2 * fy) / h, 1 - (2 * (intr.cy_px + 0.5)) / h, 0,
    0, 0, (far + near) / (far - near), (-2 * far * near) / (far - near),
    0, 0, 1, 0,
  ];
  const M = new Float32Array(16); // column-major for GL
  for (let r = 0; r < 4; r++)
    for (let c = 0; c < 4; c++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += P[r * 4 + k] * C[k * 4 + c];
      M[c * 4 + r] = s;
    }
  return M;
}

export function project(worldFromCamera, intr, p) {
  const W = worldFromCamera;
  const d = [p[0] - W[3], p[1] - W[7], p[2] - W[11]];
  const x = W[0] * d[0] + W[4] * d[1] + W[8] * d[2];
  const y = W[1] * d[0] + W[5] * d[1] + W[9] * d[2];
  const z = W[2] * d[0] + W[6] * d[1] + W[10] * d[2];
  if (z <= 0) return null;
  return [(intr.f_px * x) / z + intr.cx_px, (intr.f_px * (intr.fy_over_fx || 1) * y) / z + intr.cy_px];
}

export class ModelRenderer {
  constructor(canvas, mesh, elements) {
    const gl = canvas.getContext("webgl2", { preserveDrawingBuffer: true, premultipliedAlpha: false, alpha: true });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    this.gl = gl;
    this.canvas = canvas;
    this.mesh = mesh;
    this.n = elements.length;
    const prog = (this.prog = gl.createProgram());
    for (const [type, src] of [[gl.VERTEX_SHADER, VERT], [gl.FRAGMENT_SHADER, FRAG]]) {
      const s = gl.createShader(type);
      gl.shaderSource(s, src);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      gl.attachShader(prog, s);
    }
    gl.linkProgram(prog);
    // triangles: unshared positions, face normals, owner
    const T = mesh.T;
    const normals = new Float32Array(T * 9);
    const owners = new Float32Array(T * 3);
    for (let i = 0; i < T; i++) {
      const a = mesh.tri.subarray(i * 9, i * 9 + 9);
      const u = [a[3] - a[0], a[4] - a[1], a[5] - a[2]], v = [a[6] - a[0], a[7] - a[1], a[8] - a[2]];
      const nrm = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
      for (let k = 0; k < 3; k++) {
        normals.set(nrm, i * 9 + k * 3);
        owners[i * 3 + k] = mesh.triOwner[i];
      }
    }
    this.triVao = this._vao(mesh.tri, normals, owners);
    const eOwners = new Float32Array(mesh.K * 2);
    for (let i = 0; i < mesh.K; i++) eOwners[2 * i] = eOwners[2 * i + 1] = mesh.edgeOwner[i];
    this.edgeVao = this._vao(mesh.edges, new Float32Array(mesh.K * 6).fill(1), eOwners);
    this.base = elements.map((e) => classColor(e.ifc_class));
    this.visible = new Uint8Array(this.n).fill(1);
    this.highlight = new Map(); // element index -> [r, g, b]
    this.table = gl.createTexture();
    this.updateTable();
  }

  _vao(pos, nrm, own) {
    const gl = this.gl;
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    for (const [name, data, size] of [["position", pos, 3], ["normal", nrm, 3], ["owner", own, 1]]) {
      const loc = gl.getAttribLocation(this.prog, name);
      if (loc < 0) continue;
      const b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
    }
    gl.bindVertexArray(null);
    return vao;
  }

  setVisible(indices) {
    this.visible.fill(0);
    for (const i of indices) this.visible[i] = 1;
    this.updateTable();
  }

  updateTable() {
    const gl = this.gl;
    const w = 2048, h = Math.max(1, Math.ceil(this.n / w));
    const data = new Float32Array(w * h * 4);
    for (let i = 0; i < this.n; i++) {
      const c = this.highlight.get(i) || this.base[i];
      data.set([c[0], c[1], c[2], this.visible[i]], i * 4);
    }
    gl.bindTexture(gl.TEXTURE_2D, this.table);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, w, h, 0, gl.RGBA, gl.FLOAT, data);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  }

  // Draw for a camera; alpha < 1 ghosts the faces (model over a photo).
  draw(worldFromCamera, intr, { alpha = 1.0, edges = true, clear = [0.93, 0.94, 0.96, 1] } = {}) {
    const gl = this.gl;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clearColor(...clear);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    gl.useProgram(this.prog);
    const M = clipFromWorld(worldFromCamera, intr, 0.05, 2000);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.prog, "clipFromWorld"), false, M);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.table);
    gl.uniform1i(gl.getUniformLocation(this.prog, "table"), 0);
    gl.uniform1f(gl.getUniformLocation(this.prog, "alpha"), alpha);
    gl.uniform1f(gl.getUniformLocation(this.prog, "edgePass"), 0);
    gl.enable(gl.POLYGON_OFFSET_FILL);
    gl.polygonOffset(1, 1);
    gl.bindVertexArray(this.triVao);
    gl.drawArrays(gl.TRIANGLES, 0, this.mesh.T * 3);
    gl.disable(gl.POLYGON_OFFSET_FILL);
    if (edges) {
      gl.uniform1f(gl.getUniformLocation(this.prog, "edgePass"), 1);
      gl.uniform1f(gl.getUniformLocation(this.prog, "alpha"), Math.min(1, alpha + 0.5));
      gl.bindVertexArray(this.edgeVao);
      gl.drawArrays(gl.LINES, 0, this.mesh.K * 2);
    }
    gl.bindVertexArray(null);
  }
}

// Orbit camera around a target: yaw about z, pitch above the horizon, distance; pan moves the target.
export class OrbitView {
  constructor(canvas, renderer, bboxMin, bboxMax, onPick) {
    this.canvas = canvas;
    this.renderer = renderer;
    this.onPick = onPick;
    this.target = bboxMin.map((v, i) => (v + bboxMax[i]) / 2);
    const diag = Math.hypot(...bboxMax.map((v, i) => v - bboxMin[i]));
    this.distance = 1.5 * diag;
    this.yaw = (-60 * Math.PI) / 180;
    this.pitch = (25 * Math.PI) / 180;
    this.fovDeg = 50;
    this.markers = [];
    this._bind();
  }

  intrinsics() {
    const w = this.canvas.width, h = this.canvas.height;
    const f = (0.5 * w) / Math.tan((this.fovDeg * Math.PI) / 360);
    return { width_px: w, height_px: h, f_px: f, cx_px: (w - 1) / 2, cy_px: (h - 1) / 2, k1: 0, k2: 0, fy_over_fx: 1 };
  }

  worldFromCamera() {
    const cp = Math.cos(this.pitch), sp = Math.sin(this.pitch), cy = Math.cos(this.yaw), sy = Math.sin(this.yaw);
    const eye = [this.target[0] + this.distance * cp * cy, this.target[1] + this.distance * cp * sy, this.target[2] + this.distance * sp];
    const z = this.target.map((v, i) => v - eye[i]);
    const nz = Math.hypot(...z);
    const zf = z.map((v) => v / nz);
    let x = [zf[1] * 1 - zf[2] * 0, zf[2] * 0 - zf[0] * 1, 0]; // z cross up(0,0,1)
    const nx = Math.hypot(...x) || 1;
    x = x.map((v) => v / nx);
    const y = [zf[1] * x[2] - zf[2] * x[1], zf[2] * x[0] - zf[0] * x[2], zf[0] * x[1] - zf[1] * x[0]];
    return [x[0], y[0], zf[0], eye[0], x[1], y[1], zf[1], eye[1], x[2], y[2], zf[2], eye[2], 0, 0, 0, 1];
  }

  camera() {
    return { world_from_camera: this.worldFromCamera(), intrinsics: this.intrinsics() };
  }

  draw() {
    this.renderer.draw(this.worldFromCamera(), this.intrinsics());
    if (this.afterDraw) this.afterDraw();
  }

  _bind() {
    const c = this.canvas;
    let drag = null;
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("pointerdown", (e) => {
      drag = { x: e.clientX, y: e.clientY, moved: 0, pan: e.button === 2 || e.shiftKey };
      c.setPointerCapture(e.pointerId);
    });
    c.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.moved += Math.abs(dx) + Math.abs(dy);
      drag.x = e.clientX;
      drag.y = e.clientY;
      if (drag.pan) {
        const W = this.worldFromCamera();
        const s = (this.distance * 1.0) / this.intrinsics().f_px;
        for (let i = 0; i < 3; i++) this.target[i] -= s * (dx * W[i * 4] + dy * W[i * 4 + 1]);
      } else {
        this.yaw -= dx * 0.008;
        this.pitch = Math.max(-1.4, Math.min(1.4, this.pitch + dy * 0.008));
      }
      this.draw();
    });
    c.addEventListener("pointerup", (e) => {
      const d = drag;
      drag = null;
      if (d && d.moved < 4 && e.button === 0 && this.onPick) {
        const r = c.getBoundingClientRect();
        const u = ((e.clientX - r.left) * c.width) / r.width - 0.5;
        const v = ((e.clientY - r.top) * c.height) / r.height - 0.5;
        this.onPick(u, v, this.camera());
      }
    });
    c.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        this.distance *= Math.exp(e.deltaY * 0.001);
        this.draw();
      },
      { passive: false },
    );
  }
}
