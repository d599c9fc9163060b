// lightstage viewer: image-based relighting of per-view OLAT bases in a WebGL2 fragment shader.
// The relit image is sum_j C_j * coef_j with coef_j = sum_l A[j][l] * w_l (RGB), C_j the half-float basis
// components of the view (a texture array), A the coefficients and w the per-basis-light RGB weights: a point
// light's barycentric weights on the triangulated basis directions (the same rule as
// lightstage.training.light_basis.LightBasis.weights) plus the envmap's weights, looked up in the bundle's
// per-degree rotation table (made by lightstage.training.light_basis.rotation_table). Tonemap:
// sRGB(clip(exposure * hdr, 0, 1)), as lightstage.tonemap. No network beyond this folder.
"use strict";

(async function main() {
  const $ = (id) => document.getElementById(id);
  const api = { wanted: 0, drawn: 0, busy: false, error: null, frameTimeMs: null, renderer: "" };
  window.lightstage = api;
  const fail = (msg) => { api.error = msg; $("status").textContent = msg; };

  let M;
  try {
    const r = await fetch("manifest.json");
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    M = await r.json();
  } catch (e) {
    fail(`cannot load manifest.json (${e.message}): open this page through "lightstage view" or any web ` +
      "server; browsers do not let a page read files next to it over file://");
    return;
  }
  document.title = M.title;
  $("title").textContent = M.title;

  const canvas = $("view");
  const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, preserveDrawingBuffer: true });
  if (!gl) { fail("this browser has no WebGL2"); return; }
  const dbg = gl.getExtension("WEBGL_debug_renderer_info");
  api.renderer = dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
  api.software = /swiftshader|llvmpipe|software|softpipe/i.test(api.renderer);

  // ---- shader ------------------------------------------------------------------------------------------
  const MAX_K = Math.max(1, ...M.sets.flatMap((s) => s.views.map((v) => v.components)));
  const VS = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;
  const FS = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2DArray;
#define MAX_K ${MAX_K}
uniform sampler2DArray u_basis;
uniform vec3 u_coef[MAX_K];
uniform int u_k;
uniform ivec4 u_crop;   // x0, y0, w, h in image pixels (rows counted from the top)
uniform int u_height;
uniform float u_exposure;
out vec4 outColor;
float srgb(float x) {
  x = clamp(x, 0.0, 1.0);
  return x <= 0.0031308 ? 12.92 * x : 1.055 * pow(x, 1.0 / 2.4) - 0.055;
}
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  int x = p.x - u_crop.x;
  int y = (u_height - 1 - p.y) - u_crop.y;
  vec3 c = vec3(0.0);
  if (x >= 0 && y >= 0 && x < u_crop.z && y < u_crop.w) {
    for (int j = 0; j < MAX_K; j++) {
      if (j >= u_k) break;
      c += texelFetch(u_basis, ivec3(x, y, j), 0).rgb * u_coef[j];
    }
  }
  c *= u_exposure;
  outColor = vec4(srgb(c.r), srgb(c.g), srgb(c.b), 1.0);
}`;
  function compile(type, src) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  const prog = gl.createProgram();
  try {
    gl.attachShader(prog, compile(gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  } catch (e) { fail(`shader: ${e.message}`); return; }
  gl.useProgram(prog);
  const U = {};
  for (const n of ["u_basis", "u_coef", "u_k", "u_crop", "u_height", "u_exposure"]) U[n] = gl.getUniformLocation(prog, n);
  gl.uniform1i(U.u_basis, 0);
  gl.bindVertexArray(gl.createVertexArray());
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);

  // ---- light bases: point-light weights --------------------------------------------------------------
  function inv3(a, b, c) {  // inverse of the matrix with columns a, b, c (row-major 9 numbers)
    const m = [a[0], b[0], c[0], a[1], b[1], c[1], a[2], b[2], c[2]];
    const A = m[4] * m[8] - m[5] * m[7], B = m[5] * m[6] - m[3] * m[8], C = m[3] * m[7] - m[4] * m[6];
    const det = m[0] * A + m[1] * B + m[2] * C;
    return [A / det, (m[2] * m[7] - m[1] * m[8]) / det, (m[1] * m[5] - m[2] * m[4]) / det,
      B / det, (m[0] * m[8] - m[2] * m[6]) / det, (m[2] * m[3] - m[0] * m[5]) / det,
      C / det, (m[1] * m[6] - m[0] * m[7]) / det, (m[0] * m[4] - m[1] * m[3]) / det];
  }
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  for (const s of M.sets) {
    for (const b of s.bases) {
      b.inv = b.triangles.map((t) => inv3(b.directions[t[0]], b.directions[t[1]], b.directions[t[2]]));
    }
  }
  function pointWeights(b, dir) {  // (L,) weights, summing to 1: see LightBasis.weights
    const n = Math.hypot(dir[0], dir[1], dir[2]);
    const q = [dir[0] / n, dir[1] / n, dir[2] / n];
    const w = new Float64Array(b.lights);
    let best = -Infinity, bi = -1, bb = null;
    for (let t = 0; t < b.triangles.length; t++) {
      const m = b.inv[t];
      const l0 = m[0] * q[0] + m[1] * q[1] + m[2] * q[2];
      const l1 = m[3] * q[0] + m[4] * q[1] + m[5] * q[2];
      const l2 = m[6] * q[0] + m[7] * q[1] + m[8] * q[2];
      const tot = l0 + l1 + l2;
      if (!(tot > 0)) continue;
      const s = Math.min(l0 / tot, l1 / tot, l2 / tot);
      if (s > best) { best = s; bi = t; bb = [l0 / tot, l1 / tot, l2 / tot]; }
    }
    if (bi >= 0 && best >= -1e-9) {
      const c = bb.map((v) => Math.max(v, 0));
      const s = c[0] + c[1] + c[2];
      for (let k = 0; k < 3; k++) w[b.triangles[bi][k]] += c[k] / s;
      return w;
    }
    if (!b.rim.length) {
      let bestL = 0;
      for (let l = 1; l < b.lights; l++) if (dot(q, b.directions[l]) > dot(q, b.directions[bestL])) bestL = l;
      w[bestL] = 1;
      return w;
    }
    let bestCos = -Infinity, pick = null;
    for (const [i, j] of b.rim) {
      const a = b.directions[i], c = b.directions[j];
      const ab = dot(a, c), det = 1 - ab * ab, qa = dot(q, a), qb = dot(q, c);
      let al = Math.max((qa - ab * qb) / det, 0), be = Math.max((qb - ab * qa) / det, 0);
      if (al + be <= 0) { al = qa >= qb ? 1 : 0; be = 1 - al; }
      const s = al + be;
      al /= s; be /= s;
      const p = [al * a[0] + be * c[0], al * a[1] + be * c[1], al * a[2] + be * c[2]];
      const cos = dot(p, q) / Math.hypot(p[0], p[1], p[2]);
      if (cos > bestCos) { bestCos = cos; pick = [i, j, al, be]; }
    }
    w[pick[0]] += pick[2];
    w[pick[1]] += pick[3];
    return w;
  }
  function nearestLight(b, dir) {
    let best = 0;
    for (let l = 1; l < b.lights; l++) if (dot(dir, b.directions[l]) > dot(dir, b.directions[best])) best = l;
    return best;
  }
  const azel = (az, el) => {
    const a = az * Math.PI / 180, e = el * Math.PI / 180;
    return [Math.cos(e) * Math.cos(a), Math.cos(e) * Math.sin(a), Math.sin(e)];
  };
  const toAzel = (d) => [Math.atan2(d[1], d[0]) * 180 / Math.PI, Math.asin(Math.max(-1, Math.min(1, d[2]))) * 180 / Math.PI];

  // ---- data ----------------------------------------------------------------------------------------------
  // Progressive loading: the first view's file is fetched first and drawn; then every other view's file is
  // fetched in the background (nearest views of the shown set first) and kept, so switching views needs no
  // network. A view whose file failed is fetched again when it is shown.
  const textures = new Map();  // file -> texture (a few kept)
  const tables = new Map();  // file -> Float32Array (360 * L * 3)
  const buffers = new Map();  // file -> Promise<ArrayBuffer> of the view's components
  const loaded = new Set();
  const viewFiles = [...new Set(M.sets.flatMap((s) => s.views.map((v) => v.file)))];
  Object.assign(api, { loaded: 0, total: viewFiles.length, prefetched: false, prefetchFailed: [], firstDrawMs: null });
  async function fetchBinary(file) {
    const r = await fetch(file);
    if (!r.ok) throw new Error(`${file}: HTTP ${r.status}`);
    return r.arrayBuffer();
  }
  function showLoading() {
    $("loading").textContent = `views loaded: ${loaded.size}/${viewFiles.length}` +
      (api.prefetchFailed.length ? ` (${api.prefetchFailed.length} failed, retried when shown)` : "");
  }
  function loadView(file) {
    if (!buffers.has(file)) {
      const p = fetchBinary(file);
      buffers.set(file, p);
      p.then(() => { loaded.add(file); api.loaded = loaded.size; showLoading(); }, () => buffers.delete(file));
    }
    return buffers.get(file);
  }
  async function prefetch() {
    const order = [];
    for (const si of [S.set, ...M.sets.keys()].filter((v, i, a) => a.indexOf(v) === i)) {
      const views = M.sets[si].views, n = views.length, at = si === S.set ? S.view : 0;
      const ring = (i) => Math.min(Math.abs(i - at), n - Math.abs(i - at));
      order.push(...[...views.keys()].sort((a, b) => ring(a) - ring(b) || a - b).map((i) => views[i].file));
    }
    for (const file of order) {
      try { await loadView(file); } catch (e) { api.prefetchFailed.push(file); showLoading(); }
    }
    api.prefetched = true;
  }
  async function viewTexture(view) {
    if (textures.has(view.file)) return textures.get(view.file);
    const data = new Uint16Array(await loadView(view.file));
    const [, , w, h] = view.crop;
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, gl.RGB16F, w, h, view.components, 0, gl.RGB, gl.HALF_FLOAT, data);
    textures.set(view.file, tex);
    while (textures.size > 6) {
      const [k, t] = textures.entries().next().value;
      gl.deleteTexture(t);
      textures.delete(k);
    }
    return tex;
  }
  async function envTable(file) {
    if (!tables.has(file)) tables.set(file, new Float32Array(await fetchBinary(file)));
    return tables.get(file);
  }
  const previews = new Map();
  function preview(env) {
    if (!previews.has(env.name)) {
      const img = new Image();
      img.onload = () => drawLightmap();
      img.src = env.preview;
      previews.set(env.name, img);
    }
    return previews.get(env.name);
  }

  // ---- state and controls --------------------------------------------------------------------------------
  const S = { set: 0, view: 0, mode: "point", az: 45, el: 30, intensity: 1, envmap: M.envmaps[0].name, rot: 0,
    envInt: 1, stops: 0, ab: false, snap: false, zoom: 0 };
  const envOf = (name) => M.envmaps.find((e) => e.name === name);
  const curSet = () => M.sets[S.set];
  const curView = () => curSet().views[S.view];
  const curBasis = () => curSet().bases[curView().basis];
  function exposure() {
    const base = S.mode === "point" ? curSet().exposure : envOf(S.envmap).exposure[curSet().name];
    return base * Math.pow(2, S.stops);
  }
  api.state = () => ({ ...S, exposure: exposure(), set_name: curSet().name, view_name: curView().name });

  for (const [i, s] of M.sets.entries()) $("set").add(new Option(`${s.source}: ${s.basis_lights} basis lights`, i));
  for (const e of M.envmaps) $("envmap").add(new Option(e.name, e.name));

  function bind(id, key, parse, out, fmt) {
    const el = $(id);
    const show = () => { if (out) $(out).textContent = fmt(S[key]); };
    el.addEventListener("input", () => { S[key] = parse(el.value); onChange(key); show(); });
    el.addEventListener("change", () => { S[key] = parse(el.value); onChange(key); show(); });
    show();
  }
  bind("set", "set", Number);
  bind("view-index", "view", Number);
  bind("mode", "mode", String);
  bind("light-az", "az", Number, "light-az-out", (v) => `${v.toFixed(0)}°`);
  bind("light-el", "el", Number, "light-el-out", (v) => `${v.toFixed(0)}°`);
  bind("light-int", "intensity", Number, "light-int-out", (v) => v.toFixed(2));
  bind("envmap", "envmap", String);
  bind("env-rot", "rot", Number, "env-rot-out", (v) => `${v}°`);
  bind("env-int", "envInt", Number, "env-int-out", (v) => v.toFixed(2));
  bind("exposure", "stops", Number, "exposure-out", (v) => `${v.toFixed(1)}`);
  bind("zoom", "zoom", Number);
  $("snap").addEventListener("change", () => { S.snap = $("snap").checked; onChange("snap"); });
  $("ab").addEventListener("click", () => { S.ab = !S.ab; onChange("ab"); });
  $("measure").addEventListener("click", () => measure(100));

  function setLight(az, el) {
    S.az = Math.round(az); S.el = Math.round(el);
    $("light-az").value = S.az; $("light-el").value = S.el;
    $("light-az-out").textContent = `${S.az}°`; $("light-el-out").textContent = `${S.el}°`;
  }
  function onChange(key) {
    if (key === "set") {
      S.view = Math.min(S.view, curSet().views.length - 1);
      $("view-index").max = curSet().views.length - 1;
      $("view-index").value = S.view;
    }
    if (S.snap && ["snap", "az", "el", "set", "view"].includes(key)) {
      const b = curBasis();
      const [a, e] = toAzel(b.directions[nearestLight(b, azel(S.az, S.el))]);
      S.az = a; S.el = e;  // exactly the basis light (the sliders show it rounded)
      $("light-az").value = a; $("light-el").value = e;
      $("light-az-out").textContent = `${a.toFixed(1)}°`; $("light-el-out").textContent = `${e.toFixed(1)}°`;
    }
    requestDraw();
  }
  $("view-index").max = curSet().views.length - 1;

  // light map: lat-long picture of the envmap (top = zenith, longitude increasing to the left, as
  // docs/relighting.md) with the basis lights and the point light
  const lm = $("lightmap"), lctx = lm.getContext("2d");
  const lonToX = (lonDeg) => ((180 - lonDeg) / 360) * lm.width;
  const latToY = (latDeg) => ((90 - latDeg) / 180) * lm.height;
  function drawLightmap() {
    const W = lm.width, H = lm.height;
    lctx.fillStyle = "#000";
    lctx.fillRect(0, 0, W, H);
    const img = preview(envOf(S.envmap));
    if (img.complete && img.naturalWidth) {
      lctx.globalAlpha = S.mode === "point" ? 0.35 : 1.0;
      lctx.imageSmoothingEnabled = true;
      const shift = ((S.rot % 360) / 360) * W;  // content at longitude phi moves to phi + rot: leftwards
      lctx.drawImage(img, -shift, 0, W, H);
      lctx.drawImage(img, W - shift, 0, W, H);
      lctx.globalAlpha = 1.0;
    }
    const b = curBasis();
    lctx.fillStyle = "#ffd000";
    for (const d of b.directions) {
      const [a, e] = toAzel(d);
      lctx.fillRect(lonToX(a) - 1.5, latToY(e) - 1.5, 3, 3);
    }
    if (S.mode !== "envmap") {
      lctx.strokeStyle = "#ff3030";
      lctx.lineWidth = 2;
      lctx.beginPath();
      lctx.arc(lonToX(S.az), latToY(S.el), 6, 0, 2 * Math.PI);
      lctx.stroke();
    }
  }
  let dragging = false;
  function pick(ev) {
    const r = lm.getBoundingClientRect();
    const x = (ev.clientX - r.left) / r.width, y = (ev.clientY - r.top) / r.height;
    setLight(180 - 360 * x, 90 - 180 * y);
    onChange("az");
  }
  lm.addEventListener("pointerdown", (ev) => { dragging = true; lm.setPointerCapture(ev.pointerId); pick(ev); });
  lm.addEventListener("pointermove", (ev) => { if (dragging) pick(ev); });
  lm.addEventListener("pointerup", () => { dragging = false; });

  // ---- weights and drawing -------------------------------------------------------------------------------
  async function frameInputs() {
    // what to draw for the current state: [view, basis index set, (L*3) weights, exposure, note]
    const set = curSet(), view = curView(), basis = curBasis(), L = basis.lights;
    const dir = azel(S.az, S.el);
    if (S.ab && view.ab) {
      const bset = M.sets[view.ab.set], bview = bset.views[view.ab.view], bb = bset.bases[bview.basis];
      const l = nearestLight(bb, dir);
      const w = new Float64Array(bb.lights * 3);
      for (let c = 0; c < 3; c++) w[l * 3 + c] = S.intensity;
      const deg = Math.acos(Math.max(-1, Math.min(1, dot(dir, bb.directions[l])))) * 180 / Math.PI;
      const idx = bb.light_indices ? bb.light_indices[l] : l;
      return [bview, w, exposure(), `B: captured frame ${bview.label}, light ${idx} (${deg.toFixed(1)}° from the point light)`];
    }
    const w = new Float64Array(L * 3);
    if (S.mode !== "envmap") {
      const pw = pointWeights(basis, dir);
      for (let l = 0; l < L; l++) for (let c = 0; c < 3; c++) w[l * 3 + c] += S.intensity * pw[l];
    }
    if (S.mode !== "point") {
      const table = await envTable(envOf(S.envmap).tables[set.name][view.basis]);
      const row = ((Math.round(S.rot) % 360) + 360) % 360;
      for (let i = 0; i < L * 3; i++) w[i] += S.envInt * table[row * L * 3 + i];
    }
    return [view, w, exposure(), view.ab ? "A: relit (press A/B for the captured frame)" : "no captured frame for this view"];
  }
  function coefficients(view, w) {
    const k = view.components, L = view.coefficients.length / k;
    const out = new Float32Array(MAX_K * 3);
    for (let j = 0; j < k; j++) {
      let r = 0, g = 0, b = 0;
      for (let l = 0; l < L; l++) {
        const a = view.coefficients[j * L + l];
        r += a * w[l * 3]; g += a * w[l * 3 + 1]; b += a * w[l * 3 + 2];
      }
      out[j * 3] = r; out[j * 3 + 1] = g; out[j * 3 + 2] = b;
    }
    return out;
  }
  function drawWith(view, tex, w, exp) {
    if (canvas.width !== view.width || canvas.height !== view.height) {
      canvas.width = view.width; canvas.height = view.height;
    }
    const zoom = S.zoom || Math.max(1, Math.min(4, Math.floor(Math.min(720 / view.width, 540 / view.height))));
    canvas.style.width = `${view.width * zoom}px`;
    canvas.style.height = `${view.height * zoom}px`;
    gl.viewport(0, 0, view.width, view.height);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
    gl.uniform3fv(U.u_coef, coefficients(view, w));
    gl.uniform1i(U.u_k, view.components);
    gl.uniform4i(U.u_crop, ...view.crop);
    gl.uniform1i(U.u_height, view.height);
    gl.uniform1f(U.u_exposure, exp);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }
  let pending = false;
  function requestDraw() {
    api.wanted += 1;
    if (!pending) { pending = true; requestAnimationFrame(drawNow); }
  }
  async function drawNow() {
    if (api.busy) { requestAnimationFrame(drawNow); return; }  // a draw is awaiting data: after it
    pending = false;
    api.busy = true;
    const ticket = api.wanted;
    try {
      const [view, w, exp, note] = await frameInputs();
      const tex = await viewTexture(view);
      drawWith(view, tex, w, exp);
      showInfo(view, note, exp);
      drawLightmap();
      api.drawn = ticket;
      if (api.firstDrawMs === null) api.firstDrawMs = performance.now();
    } catch (e) {
      fail(`drawing failed: ${e.message}`);
    } finally {
      api.busy = false;
    }
    if (api.drawn !== api.wanted && !pending) { pending = true; requestAnimationFrame(drawNow); }
  }
  function showInfo(view, note, exp) {
    const set = curSet();
    $("source-info").textContent = `Source: ${set.description}. Basis lights: ${curBasis().lights} ` +
      `(this view); ${set.views.length} view(s); envmaps: ${M.envmaps.map((e) => e.name).join(", ")}.`;
    $("view-label").textContent = `${S.view + 1}/${set.views.length} ${curView().label}`;
    $("caption").textContent = `${view.label}: ${view.width}x${view.height}, ${view.components} basis ` +
      `components (relative error ${(100 * view.relative_error).toFixed(2)} %, linear HDR); exposure ` +
      `${exp.toPrecision(4)}. ${note}`;
    $("ab").disabled = !curView().ab;
    $("ab").textContent = S.ab && curView().ab ? "A/B: showing the captured frame" : "A/B: showing the relit image";
    $("ab-info").textContent = curView().ab ? "" : "A/B needs a captured frame of this view (novel views have none).";
  }

  // frame time: the whole per-frame work (weights, coefficients, draw), synchronised by a 1-pixel read
  async function measure(n) {
    const [view, w, exp] = await frameInputs();
    const tex = await viewTexture(view);
    const px = new Uint8Array(4);
    drawWith(view, tex, w, exp);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    const t0 = performance.now();
    for (let i = 0; i < n; i++) {
      const [v2, w2, e2] = await frameInputs();
      drawWith(v2, tex, w2, e2);
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    }
    const ms = (performance.now() - t0) / n;
    api.frameTimeMs = ms;
    $("timing").textContent = `frame time: ${ms.toFixed(2)} ms (${(1000 / ms).toFixed(0)} frames/s) over ${n} ` +
      `draws at ${view.width}x${view.height}, ${view.components} components; renderer: ${api.renderer}` +
      (api.software ? " (a software renderer: a GPU is much faster)" : "");
    requestDraw();
    return ms;
  }
  api.measure = measure;
  api.idle = () => api.drawn === api.wanted && !api.busy && !pending;

  requestDraw();
  const waitIdle = async () => { while (!api.idle()) await new Promise((r) => setTimeout(r, 20)); };
  await waitIdle();
  await measure(30);
  api.ready = true;
  await prefetch();
})();
