"use strict";
(function () {
  const status = document.getElementById("status");
  function fail(msg) { status.textContent = "error: " + msg; status.style.color = "#b00"; }
  let meta, bytes;
  try {
    meta = JSON.parse(document.getElementById("meta").textContent);
    const b64 = document.getElementById("data").textContent.trim();
    const bin = atob(b64);
    bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  } catch (e) { fail("cannot decode the embedded data: " + e); return; }
  const buf = bytes.buffer;
  const f32 = (off, n) => new Float32Array(buf, off, n);
  const u32 = (off, n) => new Uint32Array(buf, off, n);

  const canvas = document.getElementById("view");
  const gl = canvas.getContext("webgl2", { antialias: true, preserveDrawingBuffer: true });
  if (!gl) { fail("this browser has no WebGL2"); return; }

  // ---- shaders -------------------------------------------------------------------------------
  const VS = `#version 300 es
  in vec3 aPos; in float aVal;
  uniform mat4 uView; uniform mat4 uProj; uniform float uPointSize;
  out vec3 vEye; out float vVal;
  void main() {
    vec4 e = uView * vec4(aPos, 1.0);
    vEye = e.xyz; vVal = aVal;
    gl_Position = uProj * e;
    gl_PointSize = uPointSize;
  }`;
  const FS = `#version 300 es
  precision highp float;
  in vec3 vEye; in float vVal;
  uniform int uMode;            // 0: distance colours, 1: flat colour, 2: round points
  uniform vec3 uColor; uniform float uAlpha; uniform float uVmax;
  uniform vec3 uStops[5]; uniform float uPos[5];
  out vec4 outColor;
  vec3 ramp(float t) {
    t = clamp(t, 0.0, 1.0);
    for (int i = 0; i < 4; i++) {
      if (t <= uPos[i + 1]) return mix(uStops[i], uStops[i + 1], (t - uPos[i]) / (uPos[i + 1] - uPos[i]));
    }
    return uStops[4];
  }
  void main() {
    if (uMode == 2) {
      vec2 c = gl_PointCoord - vec2(0.5);
      if (dot(c, c) > 0.25) discard;
      outColor = vec4(uColor, 1.0);
      return;
    }
    vec3 n = normalize(cross(dFdx(vEye), dFdy(vEye)));
    vec3 toEye = normalize(-vEye);
    vec3 key = normalize(vec3(-0.45, 0.55, 1.0));
    vec3 halfv = normalize(key + toEye);
    float light = 0.22 + 0.48 * abs(dot(n, toEye)) + 0.30 * abs(dot(n, key));   // two-sided
    float spec = 0.12 * pow(abs(dot(n, halfv)), 40.0);
    vec3 base = (uMode == 0) ? ramp(vVal / uVmax) : uColor;
    outColor = vec4(min(base * light + vec3(spec), vec3(1.0)), uAlpha);
  }`;
  function compile(type, src) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  let prog;
  try {
    prog = gl.createProgram();
    gl.attachShader(prog, compile(gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, FS));
    gl.bindAttribLocation(prog, 0, "aPos");
    gl.bindAttribLocation(prog, 1, "aVal");
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  } catch (e) { fail("shader: " + e.message); return; }
  gl.useProgram(prog);
  const U = {};
  for (const name of ["uView", "uProj", "uPointSize", "uMode", "uColor", "uAlpha", "uVmax", "uStops", "uPos"]) {
    U[name] = gl.getUniformLocation(prog, name);
  }
  gl.uniform3fv(U.uStops, meta.stops.flatMap(s => s[1]));
  gl.uniform1fv(U.uPos, meta.stops.map(s => s[0]));

  // ---- geometry ------------------------------------------------------------------------------
  function layer(L, isMesh) {
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const n = isMesh ? L.vertices : L.count;
    const pb = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, pb);
    gl.bufferData(gl.ARRAY_BUFFER, f32(L.positions, 3 * n), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    if (L.values !== undefined) {
      const vb = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, vb);
      gl.bufferData(gl.ARRAY_BUFFER, f32(L.values, n), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(1);
      gl.vertexAttribPointer(1, 1, gl.FLOAT, false, 0, 0);
    } else {
      gl.disableVertexAttribArray(1);
      gl.vertexAttrib1f(1, 0.0);
    }
    let count = n;
    if (isMesh) {
      const ib = gl.createBuffer();
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, u32(L.indices, 3 * L.triangles), gl.STATIC_DRAW);
      count = 3 * L.triangles;
    }
    gl.bindVertexArray(null);
    return { vao: vao, count: count, colored: L.values !== undefined };
  }
  const recon = layer(meta.recon, true);
  const gt = meta.gt ? layer(meta.gt, true) : null;
  const pts = meta.points ? layer(meta.points, false) : null;
  if (!gt) document.getElementById("row-gt").style.display = "none";
  if (!pts) document.getElementById("row-points").style.display = "none";
  if (!recon.colored) document.getElementById("legend").style.display = "none";

  // ---- camera --------------------------------------------------------------------------------
  const up = [0, 0, 0]; up[meta.up] = 1;
  const fwd = [0, 0, 0]; fwd[(meta.up + 1) % 3] = 1;
  const side = [up[1] * fwd[2] - up[2] * fwd[1], up[2] * fwd[0] - up[0] * fwd[2], up[0] * fwd[1] - up[1] * fwd[0]];
  // The first view (and a double click) frames the bounding sphere in the narrower of the two
  // fields of view (30° vertical), with a 10% margin.
  function fitDistance() {
    const aspect = Math.max(1e-3, (canvas.clientWidth || 1) / (canvas.clientHeight || 1));
    const half = Math.atan(Math.tan(15 * Math.PI / 180) * Math.min(1, aspect));
    return 1.1 * meta.radius / Math.sin(half);
  }
  function homeView() { return { az: 0.6, el: 0.25, dist: fitDistance(), target: [0, 0, 0] }; }
  let cam = homeView();
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const norm = a => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
  function eyeDir() {
    const ce = Math.cos(cam.el), se = Math.sin(cam.el), ca = Math.cos(cam.az), sa = Math.sin(cam.az);
    return [0, 1, 2].map(i => ce * (ca * fwd[i] + sa * side[i]) + se * up[i]);
  }
  function viewMatrix() {
    const w = eyeDir();
    const eye = [0, 1, 2].map(i => cam.target[i] + cam.dist * w[i]);
    let r = cross(up, w);
    if (Math.hypot(r[0], r[1], r[2]) < 1e-6) r = side;
    r = norm(r);
    const u = cross(w, r);
    return [r[0], u[0], w[0], 0, r[1], u[1], w[1], 0, r[2], u[2], w[2], 0,
            -dot(r, eye), -dot(u, eye), -dot(w, eye), 1];
  }
  function projMatrix(aspect) {
    const f = 1 / Math.tan(0.5 * 30 * Math.PI / 180);
    const near = Math.max(cam.dist - 2.5 * meta.radius, cam.dist * 0.01), far = cam.dist + 2.5 * meta.radius;
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, 2 * far * near / (near - far), 0];
  }

  // ---- drawing -------------------------------------------------------------------------------
  const ui = {
    recon: document.getElementById("show-recon"), gt: document.getElementById("show-gt"),
    points: document.getElementById("show-points"), vmax: document.getElementById("vmax"),
  };
  ui.vmax.value = meta.vmax;
  const stopsCss = meta.stops.map(s => "rgb(" + s[1].map(c => Math.round(255 * c)).join(",") + ") " + (100 * s[0]) + "%");
  document.getElementById("bar").style.background = "linear-gradient(to right, " + stopsCss.join(", ") + ")";
  if (meta.mean !== null) document.getElementById("mean").textContent = "mean " + meta.mean.toFixed(2) + " mm";
  function updateLegend() { document.getElementById("vmax-label").textContent = Number(ui.vmax.value) + "+ mm"; }
  updateLegend();

  function resize() {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  }
  function draw() {
    resize();
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.clearColor(1, 1, 1, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);   // double-sided
    gl.uniformMatrix4fv(U.uView, false, viewMatrix());
    gl.uniformMatrix4fv(U.uProj, false, projMatrix(canvas.width / canvas.height));
    gl.uniform1f(U.uVmax, Number(ui.vmax.value));
    gl.uniform1f(U.uPointSize, Math.max(2.0, 2.0 * (window.devicePixelRatio || 1)));
    gl.disable(gl.BLEND); gl.depthMask(true);
    if (ui.recon.checked) {
      gl.uniform1i(U.uMode, recon.colored ? 0 : 1);
      gl.uniform3f(U.uColor, 0.78, 0.78, 0.77); gl.uniform1f(U.uAlpha, 1.0);
      gl.bindVertexArray(recon.vao); gl.drawElements(gl.TRIANGLES, recon.count, gl.UNSIGNED_INT, 0);
    }
    if (pts && ui.points.checked) {
      gl.uniform1i(U.uMode, 2); gl.uniform3f(U.uColor, 0.1, 0.1, 0.1); gl.uniform1f(U.uAlpha, 1.0);
      gl.bindVertexArray(pts.vao); gl.drawArrays(gl.POINTS, 0, pts.count);
    }
    if (gt && ui.gt.checked) {   // translucent ghost, drawn last without writing depth
      gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA); gl.depthMask(false);
      gl.uniform1i(U.uMode, 1); gl.uniform3f(U.uColor, 0.6, 0.6, 0.62); gl.uniform1f(U.uAlpha, 0.35);
      gl.bindVertexArray(gt.vao); gl.drawElements(gl.TRIANGLES, gt.count, gl.UNSIGNED_INT, 0);
      gl.depthMask(true); gl.disable(gl.BLEND);
    }
    gl.bindVertexArray(null);
  }
  let pending = false;
  function redraw() { if (!pending) { pending = true; requestAnimationFrame(() => { pending = false; draw(); }); } }

  // ---- interaction ---------------------------------------------------------------------------
  let drag = null;
  canvas.addEventListener("contextmenu", e => e.preventDefault());
  canvas.addEventListener("pointerdown", e => {
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
    canvas.setPointerCapture(e.pointerId); canvas.style.cursor = "grabbing";
  });
  canvas.addEventListener("pointerup", e => { drag = null; canvas.style.cursor = "grab"; });
  canvas.addEventListener("pointermove", e => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      const v = viewMatrix(), k = 2 * cam.dist * Math.tan(15 * Math.PI / 180) / canvas.clientHeight;
      const r = [v[0], v[4], v[8]], u = [v[1], v[5], v[9]];
      cam.target = [0, 1, 2].map(i => cam.target[i] - k * (dx * r[i] - dy * u[i]));
    } else {
      cam.az -= dx * 0.008;
      cam.el = Math.max(-1.55, Math.min(1.55, cam.el + dy * 0.008));
    }
    redraw();
  });
  canvas.addEventListener("wheel", e => {
    e.preventDefault();
    cam.dist = Math.max(0.05 * meta.radius, Math.min(20 * meta.radius, cam.dist * Math.exp(e.deltaY * 0.001)));
    redraw();
  }, { passive: false });
  canvas.addEventListener("dblclick", () => { cam = homeView(); redraw(); });
  for (const el of [ui.recon, ui.gt, ui.points]) el.addEventListener("change", redraw);
  ui.vmax.addEventListener("input", () => { updateLegend(); redraw(); });
  window.addEventListener("resize", redraw);

  // ---- first frame, drawn synchronously so that headless checks see it -------------------------
  try {
    draw();
    const px = new Uint8Array(4 * 64 * 64);
    gl.readPixels(Math.floor(canvas.width / 2) - 32, Math.floor(canvas.height / 2) - 32, 64, 64, gl.RGBA, gl.UNSIGNED_BYTE, px);
    let drawn = 0;
    for (let i = 0; i < px.length; i += 4) if (px[i] < 250 || px[i + 1] < 250 || px[i + 2] < 250) drawn++;
    const err = gl.getError();
    if (err !== gl.NO_ERROR) { fail("WebGL error " + err); return; }
    status.textContent = "ready webgl2 triangles=" + meta.recon.triangles + " centre_pixels_drawn=" + drawn;
    status.dataset.ready = "1";
  } catch (e) { fail(e.message); }
})();
